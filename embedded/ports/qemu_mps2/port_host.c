/* The host's port of replay.c: lines to stdout, the status as the exit code. */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

int replay_main(void);

void port_line(const char *text)
{
    fputs(text, stdout);
    fputc('\n', stdout);
}

void port_exit(int status)
{
    fflush(stdout);
    exit(status);
}

/* No instruction count on the host. */
uint32_t port_ticks(void)
{
    return 0;
}

uint32_t port_calibrate(uint32_t *instructions)
{
    *instructions = 0;
    return 0;
}

int main(void)
{
    port_exit(replay_main());
    return 0;
}
