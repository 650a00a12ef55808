/* cochlea embedded runtime, POSIX port: the HAL (see hal_posix.h). */
/* ppoll (a sub-millisecond read timeout) and the fast baud rates are Linux's and the BSDs';
 * elsewhere poll's whole milliseconds do. */
#define _GNU_SOURCE
#include "hal_posix.h"

#include <errno.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

static speed_t speed_of(long baud, int *ok)
{
    *ok = 1;
    switch (baud) {
    case 9600: return B9600;
    case 57600: return B57600;
    case 115200: return B115200;
#ifdef B1000000
    case 1000000: return B1000000;
#endif
#ifdef B2000000
    case 2000000: return B2000000;
#endif
#ifdef B3000000
    case 3000000: return B3000000;
#endif
#ifdef B4000000
    case 4000000: return B4000000;
#endif
    default: *ok = 0; return B0;
    }
}

/* The emulator's socket (cochlea-emulator --listen): "unix:PATH" or "socket://HOST:PORT".
 * Connected (blocking: a listening emulator accepts at once), then non-blocking as the serial
 * device is. */
static int open_socket(cochlea_posix_port *port, const char *path)
{
    int fd = -1, saved;
    if (strncmp(path, "unix:", 5) == 0) {
        struct sockaddr_un addr;
        const size_t len = strlen(path + 5);
        memset(&addr, 0, sizeof addr);
        addr.sun_family = AF_UNIX;
        if (len == 0 || len >= sizeof addr.sun_path) {
            errno = ENAMETOOLONG;
            return -1;
        }
        memcpy(addr.sun_path, path + 5, len);
        fd = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
        if (fd < 0 || connect(fd, (const struct sockaddr *)&addr, sizeof addr) != 0) {
            goto fail;
        }
    } else {
        char host[256];
        const char *rest = path + 9, *colon = strrchr(rest, ':');
        const char *service = colon ? colon + 1 : "";
        struct addrinfo hints, *found = 0, *a;
        size_t n = colon ? (size_t)(colon - rest) : 0;
        int rc, one = 1;
        if (n >= 2 && rest[0] == '[' && rest[n - 1] == ']') { /* [::1]:PORT */
            ++rest;
            n -= 2;
        }
        if (n == 0 || n >= sizeof host || *service == 0
            || strspn(service, "0123456789") != strlen(service)) {
            errno = EINVAL;
            return -1;
        }
        memcpy(host, rest, n);
        host[n] = 0;
        memset(&hints, 0, sizeof hints);
        hints.ai_family = AF_UNSPEC;
        hints.ai_socktype = SOCK_STREAM;
        hints.ai_flags = AI_NUMERICSERV;
        rc = getaddrinfo(host, service, &hints, &found);
        if (rc != 0) {
            errno = rc == EAI_SYSTEM ? errno : EHOSTUNREACH;
            return -1;
        }
        errno = ECONNREFUSED;
        for (a = found; a; a = a->ai_next) {
            fd = socket(a->ai_family, a->ai_socktype | SOCK_CLOEXEC, a->ai_protocol);
            if (fd >= 0 && connect(fd, a->ai_addr, a->ai_addrlen) == 0) {
                break;
            }
            if (fd >= 0) {
                saved = errno;
                close(fd);
                errno = saved;
                fd = -1;
            }
        }
        freeaddrinfo(found);
        if (fd < 0) {
            return -1;
        }
        /* Each write is a whole frame: sent at once, not held for the previous one's ACK. */
        (void)setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    }
    if (fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK) != 0) {
        goto fail;
    }
    port->fd = fd;
    port->socket = 1;
    return 0;
fail:
    saved = errno;
    if (fd >= 0) {
        close(fd);
    }
    errno = saved;
    return -1;
}

int cochlea_posix_open(cochlea_posix_port *port, const char *path, long baud)
{
    struct termios tio;
    int ok;
    const speed_t speed = speed_of(baud, &ok);
    port->fd = -1;
    port->baud = baud;
    port->socket = 0;
    if (!ok) {
        errno = EINVAL;
        return -1;
    }
    if (strncmp(path, "unix:", 5) == 0 || strncmp(path, "socket://", 9) == 0) {
        return open_socket(port, path); /* the baud rate is the emulator's --baud */
    }
    port->fd = open(path, O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
    if (port->fd < 0) {
        return -1;
    }
    if (tcgetattr(port->fd, &tio) != 0) {
        close(port->fd);
        port->fd = -1;
        return -1;
    }
    cfmakeraw(&tio);
    tio.c_cflag |= CLOCAL | CREAD;
    tio.c_cflag &= (tcflag_t)~(CSTOPB | PARENB | CRTSCTS);
    tio.c_cc[VMIN] = 0;
    tio.c_cc[VTIME] = 0;
    if (cfsetispeed(&tio, speed) != 0 || cfsetospeed(&tio, speed) != 0 ||
        tcsetattr(port->fd, TCSANOW, &tio) != 0) {
        const int saved = errno;
        close(port->fd);
        port->fd = -1;
        errno = saved;
        return -1;
    }
    tcflush(port->fd, TCIOFLUSH);
    return 0;
}

void cochlea_posix_close(cochlea_posix_port *port)
{
    if (port->fd >= 0) {
        close(port->fd);
        port->fd = -1;
    }
}

static int64_t now_ns(void *ctx)
{
    struct timespec ts;
    (void)ctx;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static void wait_until_ns(void *ctx, int64_t deadline)
{
    struct timespec ts;
    (void)ctx;
    ts.tv_sec = (time_t)(deadline / 1000000000LL);
    ts.tv_nsec = (long)(deadline % 1000000000LL);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {
    }
}

static long serial_write(void *ctx, const uint8_t *data, size_t n)
{
    const cochlea_posix_port *port = ctx;
    size_t done = 0;
    const int64_t give_up = now_ns(ctx) + 100000000LL; /* a stuck adapter: 100 ms */
    while (done < n) {
        const ssize_t w = write(port->fd, data + done, n - done);
        if (w > 0) {
            done += (size_t)w;
            continue;
        }
        if (w < 0 && errno != EAGAIN && errno != EINTR) {
            return -1;
        }
        if (now_ns(ctx) > give_up) {
            return -1;
        }
        {
            struct pollfd p = {port->fd, POLLOUT, 0};
            (void)poll(&p, 1, 1);
        }
    }
    return (long)done;
}

static long serial_read(void *ctx, uint8_t *data, size_t n, int64_t timeout_ns)
{
    const cochlea_posix_port *port = ctx;
    const int64_t deadline = now_ns(ctx) + timeout_ns;
    for (;;) {
        struct pollfd p = {port->fd, POLLIN, 0};
        struct timespec ts;
        const int64_t left = deadline - now_ns(ctx);
        ssize_t got;
        int ready;
        if (left <= 0) {
            p.revents = 0;
            ready = poll(&p, 1, 0);
        } else {
#if defined(__linux__)
            ts.tv_sec = (time_t)(left / 1000000000LL);
            ts.tv_nsec = (long)(left % 1000000000LL);
            ready = ppoll(&p, 1, &ts, NULL);
#else
            (void)ts;
            ready = poll(&p, 1, (int)((left + 999999) / 1000000));
#endif
        }
        if (ready < 0) {
            if (errno == EINTR) {
                continue;
            }
            return -1;
        }
        if (ready == 0) {
            return 0;
        }
        if (p.revents & (POLLERR | POLLNVAL)) {
            return -1;
        }
        got = read(port->fd, data, n);
        if (got > 0) {
            return (long)got;
        }
        if (got == 0 || (p.revents & POLLHUP)) {
            return -1; /* the other end closed (the emulator or the adapter is gone) */
        }
        if (errno != EAGAIN && errno != EINTR) {
            return -1;
        }
        if (left <= 0) {
            return 0;
        }
    }
}

static void discard_input(void *ctx)
{
    const cochlea_posix_port *port = ctx;
    if (port->socket) { /* no tty queue: read what is there (an end of stream stays seen) */
        uint8_t drop[256];
        while (recv(port->fd, drop, sizeof drop, MSG_DONTWAIT) > 0) {
        }
        return;
    }
    tcflush(port->fd, TCIFLUSH);
}

void cochlea_posix_hal(cochlea_hal *hal, cochlea_posix_port *port)
{
    hal->ctx = port;
    hal->serial_write = serial_write;
    hal->serial_read = serial_read;
    hal->serial_discard_input = discard_input;
    hal->rs485_direction = NULL;
    hal->now_ns = now_ns;
    hal->wait_until_ns = wait_until_ns;
}
