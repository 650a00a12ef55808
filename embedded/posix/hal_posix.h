/* cochlea embedded runtime, POSIX port: the HAL (cochlea_rt.h) on a serial device with
 * termios, CLOCK_MONOTONIC and clock_nanosleep. */
#ifndef COCHLEA_HAL_POSIX_H
#define COCHLEA_HAL_POSIX_H

#include "cochlea_rt.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef struct {
    int fd;
    long baud;
    int socket; /* 1: the emulator's socket (unix:PATH, socket://HOST:PORT), not a tty */
} cochlea_posix_port;

/* Open path raw, 8N1, at baud (the Dynamixel rates 9600 .. 4500000 the platform knows; a
 * pseudo-terminal takes any). 0, or -1 with errno set (EINVAL: a baud rate it cannot set).
 * "unix:PATH" or "socket://HOST:PORT" connects to cochlea-emulator --listen instead (the same
 * bytes on a stream socket; baud is still checked, the emulator's --baud times the wire). */
int cochlea_posix_open(cochlea_posix_port *port, const char *path, long baud);
void cochlea_posix_close(cochlea_posix_port *port);
/* The HAL whose callbacks use port (the RS-485 direction is the adapter's: NULL). */
void cochlea_posix_hal(cochlea_hal *hal, cochlea_posix_port *port);

#ifdef __cplusplus
}
#endif

#endif /* COCHLEA_HAL_POSIX_H */
