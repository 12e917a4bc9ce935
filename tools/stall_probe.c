/* stall_probe: how late a lone SCHED_FIFO thread wakes from periodic absolute sleeps.
 *
 * The same kind of wake-up as JACK's dummy driver timer (a real-time thread sleeping to the
 * next period): a wake-up later than the period's slack is an xrun that no JACK client
 * can prevent. tools/bench_engine.py --audio runs it beside the live runs.
 *
 * usage: stall_probe PRIORITY PERIOD_US SECONDS THRESHOLD_US [CPU]
 * (CPU: pin the thread to that CPU; a virtual machine's CPUs stall one at a time, so the
 * benchmark runs one probe per CPU.)
 * prints one line per wake-up later than THRESHOLD_US: "<CLOCK_MONOTONIC s> <late us>",
 * then "max <late us> n <wake-ups>". Exit 0 (1 on bad arguments).
 */
#define _GNU_SOURCE
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

static long long ns(const struct timespec *t) { return t->tv_sec * 1000000000LL + t->tv_nsec; }

int main(int argc, char **argv) {
    if (argc != 5 && argc != 6) {
        fprintf(stderr, "usage: stall_probe PRIORITY PERIOD_US SECONDS THRESHOLD_US [CPU]\n");
        return 1;
    }
    if (argc == 6) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(atoi(argv[5]), &set);
        if (sched_setaffinity(0, sizeof set, &set) != 0) perror("sched_setaffinity");
    }
    int prio = atoi(argv[1]);
    double period_us = atof(argv[2]), secs = atof(argv[3]), thr_us = atof(argv[4]);
    if (prio > 0) {
        struct sched_param sp = {.sched_priority = prio};
        if (sched_setscheduler(0, SCHED_FIFO, &sp) != 0) perror("sched_setscheduler");
    }
    struct timespec now, next;
    clock_gettime(CLOCK_MONOTONIC, &now);
    long long t = ns(&now), period = (long long)(period_us * 1000.0);
    long long n = (long long)(secs * 1e6 / period_us), worst = 0;
    for (long long i = 1; i <= n; i++) {
        long long due = t + i * period;
        next.tv_sec = due / 1000000000LL;
        next.tv_nsec = due % 1000000000LL;
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
        clock_gettime(CLOCK_MONOTONIC, &now);
        long long late = ns(&now) - due;
        if (late > worst) worst = late;
        if (late > thr_us * 1000.0) printf("%.6f %lld\n", ns(&now) * 1e-9, late / 1000);
    }
    printf("max %lld n %lld\n", worst / 1000, n);
    return 0;
}
