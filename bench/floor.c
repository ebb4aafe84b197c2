/* The round trip alone in compiled code (bench/sample_cost.py --floor): what no server,
 * in any language, pays less than for one arm's polls over `socket://` on this machine.
 *
 *     floor PORT N HEXPACKET REPLYSIZE
 *
 * Connects to 127.0.0.1:PORT (TCP_NODELAY), then N times: sleeps to the next slot of a 2 ms
 * grid (an absolute CLOCK_MONOTONIC sleep), writes the packet, reads until REPLYSIZE bytes.
 * Prints this process's user and system CPU time a poll, in microseconds: "USER SYSTEM".
 * The bytes are the codec's (the caller passes them), the loop is `_floor_blocking`'s. */
#include <arpa/inet.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

static double seconds(struct timeval t) { return t.tv_sec + t.tv_usec * 1e-6; }

int main(int argc, char **argv) {
    if (argc != 5) {
        fprintf(stderr, "usage: floor PORT N HEXPACKET REPLYSIZE\n");
        return 2;
    }
    int port = atoi(argv[1]), n = atoi(argv[2]), size = atoi(argv[4]);
    size_t len = strlen(argv[3]) / 2;
    unsigned char packet[256], reply[256];
    if (len > sizeof packet || size <= 0 || size > (int)sizeof reply || n <= 0) {
        fprintf(stderr, "floor: bad arguments\n");
        return 2;
    }
    for (size_t i = 0; i < len; i++) {
        unsigned int byte;
        sscanf(argv[3] + 2 * i, "%2x", &byte);
        packet[i] = (unsigned char)byte;
    }
    int sock = socket(AF_INET, SOCK_STREAM, 0);
    struct sockaddr_in addr = {0};
    addr.sin_family = AF_INET;
    addr.sin_port = htons((unsigned short)port);
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (sock < 0 || connect(sock, (struct sockaddr *)&addr, sizeof addr) != 0) {
        perror("floor: connect");
        return 1;
    }
    int one = 1;
    setsockopt(sock, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    struct timespec slot;
    clock_gettime(CLOCK_MONOTONIC, &slot);
    struct rusage r0, r1;
    getrusage(RUSAGE_SELF, &r0);
    for (int k = 0; k < n; k++) {
        slot.tv_nsec += 2000000;
        if (slot.tv_nsec >= 1000000000) {
            slot.tv_nsec -= 1000000000;
            slot.tv_sec += 1;
        }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &slot, NULL);
        if (write(sock, packet, len) != (ssize_t)len) {
            perror("floor: write");
            return 1;
        }
        for (int got = 0; got < size;) {
            ssize_t m = read(sock, reply + got, (size_t)(size - got));
            if (m <= 0) {
                perror("floor: read");
                return 1;
            }
            got += (int)m;
        }
    }
    getrusage(RUSAGE_SELF, &r1);
    printf("%.1f %.1f\n", 1e6 * (seconds(r1.ru_utime) - seconds(r0.ru_utime)) / n,
           1e6 * (seconds(r1.ru_stime) - seconds(r0.ru_stime)) / n);
    close(sock);
    return 0;
}
