/* The host's port of replay.c: lines to stdout, the status as the exit code. */
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

int main(void)
{
    port_exit(replay_main());
    return 0;
}
