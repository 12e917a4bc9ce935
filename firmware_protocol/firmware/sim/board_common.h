/*
 * board_common.h -- what the emulated boards (hapkit_board.c, pantograph_board.c) share
 * outside their physics: the pseudo-terminal the host opens, simavr's log (errors to
 * stderr, warnings counted for the report) and the command line's numbers. Static: each
 * board is one translation unit (include it once, after <stdio.h> and simavr's headers).
 */
#ifndef BOARD_COMMON_H
#define BOARD_COMMON_H

#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <unistd.h>

#include "sim_avr.h"

/* A new raw, non-blocking pseudo-terminal (its master fd); `link`, when given, is made a
 * symbolic link to it (atomically: a .new link renamed over it); prints "PORT <path>". */
static int board_open_pty(const char *link, const char *who)
{
    int fd = posix_openpt(O_RDWR | O_NOCTTY);
    int slave;
    struct termios t;
    char *name;
    if (fd < 0 || grantpt(fd) || unlockpt(fd) || !(name = ptsname(fd))) {
        fprintf(stderr, "%s: pty: %s\n", who, strerror(errno));
        exit(1);
    }
    slave = open(name, O_RDWR | O_NOCTTY);
    if (slave >= 0) {
        tcgetattr(slave, &t);
        cfmakeraw(&t);
        tcsetattr(slave, TCSANOW, &t);
        close(slave); /* the raw settings stay with the pty */
    }
    fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK);
    if (link) {
        char tmp[4096];
        snprintf(tmp, sizeof tmp, "%s.new", link);
        unlink(tmp);
        if (symlink(name, tmp) == 0) {
            rename(tmp, link);
        }
    }
    printf("PORT %s\n", link ? link : name);
    fflush(stdout);
    return fd;
}

/* simavr's messages: errors go to stderr (stdout carries only the PORT line and the
 * report); its warnings and traces are not the user's business (e.g. "TIMER:
 * avr_timer_write_ocr-1 mode 0 UNSUPPORTED" when the firmware writes OCR1A before it sets
 * the timer's mode) and are only counted, the last one kept, for the report. */
static struct {
    uint64_t warnings;
    char last[160];
} simlog;

static void log_stderr(avr_t *a, const int level, const char *format, va_list ap)
{
    (void)a;
    if (level <= LOG_ERROR) {
        vfprintf(stderr, format, ap);
    } else if (level == LOG_WARNING) {
        size_t n;
        simlog.warnings++;
        vsnprintf(simlog.last, sizeof simlog.last, format, ap);
        n = strlen(simlog.last);
        while (n > 0 && (simlog.last[n - 1] == '\n' || simlog.last[n - 1] == '\r')) {
            simlog.last[--n] = 0;
        }
    }
}

/* The last simavr warning as a JSON string's contents on `f` (quotes and backslashes
 * escaped, control characters as spaces). */
static void simlog_json(FILE *f)
{
    const char *c;
    for (c = simlog.last; *c; c++) {
        if (*c == '"' || *c == '\\') {
            fputc('\\', f);
        }
        fputc((unsigned char)*c < 0x20 ? ' ' : *c, f);
    }
}

/* The number `s` of option `name`; exits 2 (bad input) when it is not a finite one. */
static double board_num(const char *s, const char *name, const char *who)
{
    char *end;
    double v = strtod(s, &end);
    if (*s == 0 || *end != 0 || !isfinite(v)) {
        fprintf(stderr, "%s: %s: not a number: %s\n", who, name, s);
        exit(2);
    }
    return v;
}

#endif /* BOARD_COMMON_H */
