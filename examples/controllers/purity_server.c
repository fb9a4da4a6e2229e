/* A sorting controller in C: purity mode over vcyto's wire protocol (docs/wire-protocol.md).
 *
 * Plain C99 and POSIX sockets, no library beyond libc and libm. Build and run:
 *
 *     cc -std=c99 -O2 -Wall -o purity_server examples/controllers/purity_server.c -lm
 *     ./purity_server --listen tcp:127.0.0.1:7070 &
 *     vcyto stream --model rom --count 100 --controller-connect tcp:127.0.0.1:7070
 *
 * or let vcyto start it (it says where to listen through {address} and VCYTO_CONTROLLER_ADDRESS):
 *
 *     vcyto stream --model rom --count 100 --controller-exec "./purity_server --once"
 *
 * `--spin SECONDS` polls for the next message for that long after the last one before it sleeps in read(): in
 * paced real time (vcyto stream --realtime) a sleeping process wakes late often enough to miss deadlines
 * (docs/controllers.md); a polling one keeps a processor busy.
 *
 * It listens on 127.0.0.1 unless told otherwise (an open port lets anyone who reaches it drive the sorter).
 * The JSON reader is minimal: it finds a key by its quoted name anywhere in the message, which suffices for
 * vcyto's messages (no key repeats within one); a controller for production would use a JSON library.
 */
#define _POSIX_C_SOURCE 200809L
#include <arpa/inet.h>
#include <errno.h>
#include <math.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <time.h>
#include <unistd.h>

#define PROTOCOL "vcyto-controller"
#define VERSION 1
#define MAX_MESSAGE (1u << 20)      /* bytes of JSON in one frame */
#define REORDER_SLACK 1e-3          /* s: recent events are kept this much beyond the envelope's reach */

/* ---- a minimal JSON reader for vcyto's flat messages ---- */

/* The text just after `"key":` (white space skipped), or NULL. */
static const char *json_value(const char *json, const char *key) {
    size_t n = strlen(key);
    for (const char *p = strchr(json, '"'); p != NULL; p = strchr(p + 1, '"')) {
        if (strncmp(p + 1, key, n) == 0 && p[n + 1] == '"') {
            const char *q = p + n + 2;
            while (*q == ' ' || *q == '\t' || *q == '\n' || *q == '\r') q++;
            if (*q != ':') continue;
            q++;
            while (*q == ' ' || *q == '\t' || *q == '\n' || *q == '\r') q++;
            return q;
        }
    }
    return NULL;
}

static int json_number(const char *json, const char *key, double *out) {
    const char *v = json_value(json, key);
    char *end;
    if (v == NULL) return 0;
    *out = strtod(v, &end);
    return end != v;
}

static int json_integer(const char *json, const char *key, long long *out) {
    const char *v = json_value(json, key);
    char *end;
    if (v == NULL) return 0;
    *out = strtoll(v, &end, 10);
    return end != v;
}

/* A string value without escapes (vcyto's types and classes), copied into out. */
static int json_string(const char *json, const char *key, char *out, size_t size) {
    const char *v = json_value(json, key);
    size_t i = 0;
    if (v == NULL || *v != '"') return 0;
    for (v++; *v != '"' && *v != '\0'; v++) {
        if (*v == '\\' || i + 1 >= size) return 0;
        out[i++] = *v;
    }
    out[i] = '\0';
    return *v == '"';
}

/* An array of two numbers, such as the envelope [low, high]. */
static int json_pair(const char *json, const char *key, double out[2]) {
    const char *v = json_value(json, key);
    char *end;
    if (v == NULL || *v != '[') return 0;
    out[0] = strtod(v + 1, &end);
    if (end == v + 1) return 0;
    while (*end == ' ' || *end == ',') end++;
    v = end;
    out[1] = strtod(v, &end);
    return end != v;
}

/* ---- framing: 4-byte big-endian length, then the JSON ---- */

static double spin_seconds = 0.0;     /* --spin: how long to poll for the next message before sleeping in read */

static double now_seconds(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

/* Wait until fd is readable, polling for up to spin_seconds first: a process asleep in read() wakes some tens of
   microseconds to milliseconds after the data arrives (the scheduler's tail), a polling one at once. */
static void await_readable(int fd) {
    if (spin_seconds <= 0.0) return;
    char probe;
    double until = now_seconds() + spin_seconds;
    do {
        ssize_t got = recv(fd, &probe, 1, MSG_PEEK | MSG_DONTWAIT);
        if (got >= 0 || (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)) return;
    } while (now_seconds() < until);
}

static int read_full(int fd, void *buffer, size_t n) {
    char *p = buffer;
    while (n > 0) {
        await_readable(fd);
        ssize_t got = read(fd, p, n);
        if (got < 0 && errno == EINTR) continue;
        if (got <= 0) return 0;
        p += got;
        n -= (size_t)got;
    }
    return 1;
}

static int write_full(int fd, const void *buffer, size_t n) {
    const char *p = buffer;
    while (n > 0) {
        ssize_t put = write(fd, p, n);
        if (put < 0 && errno == EINTR) continue;
        if (put <= 0) return 0;
        p += put;
        n -= (size_t)put;
    }
    return 1;
}

/* The next message as a NUL-terminated string (free it), or NULL when the connection ends. */
static char *receive(int fd) {
    unsigned char header[4];
    if (!read_full(fd, header, 4)) return NULL;
    uint32_t length = ((uint32_t)header[0] << 24) | ((uint32_t)header[1] << 16) | ((uint32_t)header[2] << 8) | header[3];
    if (length == 0 || length > MAX_MESSAGE) {
        fprintf(stderr, "purity_server: a frame of %u bytes (at most %u)\n", length, MAX_MESSAGE);
        return NULL;
    }
    char *body = malloc(length + 1);
    if (body == NULL || !read_full(fd, body, length)) {
        free(body);
        return NULL;
    }
    body[length] = '\0';
    return body;
}

static int send_message(int fd, const char *json) {
    size_t n = strlen(json);
    unsigned char header[4] = {(unsigned char)(n >> 24), (unsigned char)(n >> 16), (unsigned char)(n >> 8),
                               (unsigned char)n};
    /* one write for header and body: one packet on the wire */
    char *frame = malloc(n + 4);
    if (frame == NULL) return 0;
    memcpy(frame, header, 4);
    memcpy(frame + 4, json, n);
    int ok = write_full(fd, frame, n + 4);
    free(frame);
    return ok;
}

/* ---- purity mode ---- */

typedef struct {
    long long event_id;
    int type_two;                /* classification "II" */
    double arrival;
    int sorted;                  /* its decision stands as a sort */
    double pulse_on;
} Recent;

typedef struct {
    double delay, velocity, lead, pulse, low, high, reach;
    Recent *recent;
    size_t count, capacity;
} Purity;

static int purity_start(Purity *c, const char *hello) {
    double envelope[2], timing_error;
    if (!(json_number(hello, "sort_delay", &c->delay) && json_number(hello, "reference_velocity", &c->velocity) &&
          json_number(hello, "lead", &c->lead) && json_number(hello, "pulse", &c->pulse) &&
          json_number(hello, "timing_error", &timing_error) && json_pair(hello, "envelope", envelope)))
        return 0;
    double widen = 2 * timing_error;
    c->low = envelope[0] - widen;
    c->high = envelope[1] + widen;
    c->reach = fmax(fmax(c->high, -c->low), 0.0);
    c->count = 0;
    return 1;
}

/* Append one decision object to out (pulse null unless sorted). */
static size_t put_decision(char *out, size_t at, long long id, const char *action, double arrival, double on,
                           double off) {
    if (strcmp(action, "sort") == 0)
        return at + (size_t)sprintf(out + at, "%s{\"event_id\":%lld,\"action\":\"sort\",\"arrival\":%.17g,"
                                    "\"pulse_on\":%.17g,\"pulse_off\":%.17g}", at > 0 ? "," : "", id, arrival, on, off);
    return at + (size_t)sprintf(out + at, "%s{\"event_id\":%lld,\"action\":\"%s\",\"arrival\":%.17g,"
                                "\"pulse_on\":null,\"pulse_off\":null}", at > 0 ? "," : "", id, action, arrival);
}

/* The decisions answering one event, as the text of a JSON array's items (malloc'd), or NULL. */
static char *purity_event(Purity *c, long long id, double time, double velocity, int type_two) {
    double arrival = time + c->delay * c->velocity / fmax(velocity, 1e-9);
    size_t kept = 0;
    for (size_t i = 0; i < c->count; i++)           /* forget events too far back to coincide */
        if (c->recent[i].arrival >= arrival - c->reach - REORDER_SLACK) c->recent[kept++] = c->recent[i];
    c->count = kept;
    char *out = malloc(160 * (c->count + 1) + 1);
    if (out == NULL) return NULL;
    size_t at = 0;
    out[0] = '\0';
    Recent self = {id, type_two, arrival, 0, NAN};
    if (type_two) {
        int blocked = 0;
        for (size_t i = 0; i < c->count && !blocked; i++) {
            double offset = c->recent[i].arrival - arrival;
            blocked = !c->recent[i].type_two && c->low <= offset && offset <= c->high;
        }
        double on = arrival - c->lead, off = on + c->pulse;
        if (blocked || off <= time) {
            at = put_decision(out, at, id, "abort", arrival, 0, 0);
        } else {
            at = put_decision(out, at, id, "sort", arrival, on, off);
            self.sorted = 1;
            self.pulse_on = on;
        }
    } else {
        for (size_t i = 0; i < c->count; i++) {
            Recent *other = &c->recent[i];
            double offset = arrival - other->arrival;
            if (other->sorted && other->pulse_on > time && c->low <= offset && offset <= c->high) {
                other->sorted = 0;
                at = put_decision(out, at, other->event_id, "abort", other->arrival, 0, 0);
            }
        }
        at = put_decision(out, at, id, "pass", arrival, 0, 0);
    }
    if (c->count == c->capacity) {
        c->capacity = c->capacity ? 2 * c->capacity : 64;
        Recent *grown = realloc(c->recent, c->capacity * sizeof *grown);
        if (grown == NULL) {
            free(out);
            return NULL;
        }
        c->recent = grown;
    }
    c->recent[c->count++] = self;
    return out;
}

/* ---- one run: handshake, events, end ---- */

static void serve_connection(int fd) {
    Purity controller = {0};
    int started = 0;
    char *message;
    while ((message = receive(fd)) != NULL) {
        char type[32], protocol[64], classification[8];
        double version = 0, time, velocity;
        long long id;
        int go_on = 1;
        if (!json_string(message, "type", type, sizeof type)) {
            send_message(fd, "{\"type\":\"error\",\"message\":\"a message without a type\"}");
            go_on = 0;
        } else if (strcmp(type, "hello") == 0) {
            if (!json_string(message, "protocol", protocol, sizeof protocol) || strcmp(protocol, PROTOCOL) != 0 ||
                !json_number(message, "version", &version) || version != VERSION) {
                send_message(fd, "{\"type\":\"error\",\"message\":\"this controller speaks vcyto-controller "
                                 "version 1\"}");
                go_on = 0;
            } else if (!purity_start(&controller, message)) {
                send_message(fd, "{\"type\":\"error\",\"message\":\"the hello lacks a device fact\"}");
                go_on = 0;
            } else {
                started = 1;
                send_message(fd, "{\"type\":\"welcome\",\"protocol\":\"vcyto-controller\",\"version\":1,"
                                 "\"name\":\"purity_server.c\",\"software\":\"1.0\",\"capabilities\":[\"decisions\"]}");
            }
        } else if (strcmp(type, "event") == 0 && started && json_integer(message, "event_id", &id) &&
                   json_number(message, "time", &time) && json_number(message, "velocity", &velocity) &&
                   json_string(message, "classification", classification, sizeof classification)) {
            char *items = purity_event(&controller, id, time, velocity, strcmp(classification, "II") == 0);
            char *answer = items ? malloc(strlen(items) + 64) : NULL;
            if (answer == NULL) {
                send_message(fd, "{\"type\":\"error\",\"message\":\"out of memory\"}");
                go_on = 0;
            } else {
                sprintf(answer, "{\"type\":\"decisions\",\"event_id\":%lld,\"decisions\":[%s]}", id, items);
                go_on = send_message(fd, answer);
            }
            free(items);
            free(answer);
        } else if (strcmp(type, "end") == 0) {
            send_message(fd, "{\"type\":\"bye\"}");
            go_on = 0;
        } else if (strcmp(type, "error") == 0) {
            fprintf(stderr, "purity_server: vcyto reported an error: %s\n", message);
            go_on = 0;
        } else {
            send_message(fd, "{\"type\":\"error\",\"message\":\"unexpected or incomplete message\"}");
            go_on = 0;
        }
        free(message);
        if (!go_on) break;
    }
    free(controller.recent);
}

/* ---- listening ---- */

static int listen_on(const char *address) {
    int fd = -1;
    if (strncmp(address, "unix:", 5) == 0) {
        struct sockaddr_un where = {0};
        where.sun_family = AF_UNIX;
        if (strlen(address + 5) >= sizeof where.sun_path) return -1;
        strcpy(where.sun_path, address + 5);
        unlink(where.sun_path);
        fd = socket(AF_UNIX, SOCK_STREAM, 0);
        if (fd < 0 || bind(fd, (struct sockaddr *)&where, sizeof where) != 0) return -1;
    } else if (strncmp(address, "tcp:", 4) == 0) {
        char host[64];
        const char *colon = strrchr(address + 4, ':');
        if (colon == NULL || (size_t)(colon - (address + 4)) >= sizeof host) return -1;
        memcpy(host, address + 4, (size_t)(colon - (address + 4)));
        host[colon - (address + 4)] = '\0';
        struct sockaddr_in where = {0};
        where.sin_family = AF_INET;
        where.sin_port = htons((uint16_t)atoi(colon + 1));
        if (inet_pton(AF_INET, strcmp(host, "localhost") == 0 ? "127.0.0.1" : host, &where.sin_addr) != 1) return -1;
        fd = socket(AF_INET, SOCK_STREAM, 0);
        int yes = 1;
        if (fd < 0 || setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes) != 0 ||
            bind(fd, (struct sockaddr *)&where, sizeof where) != 0)
            return -1;
    } else {
        return -1;
    }
    return listen(fd, 1) == 0 ? fd : -1;
}

int main(int argc, char **argv) {
    const char *address = getenv("VCYTO_CONTROLLER_ADDRESS");
    int once = 0;
    if (address == NULL) address = "tcp:127.0.0.1:7070";
    for (int i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--listen") == 0 && i + 1 < argc) {
            address = argv[++i];
        } else if (strcmp(argv[i], "--once") == 0) {
            once = 1;
        } else if (strcmp(argv[i], "--spin") == 0 && i + 1 < argc) {
            char *end;
            spin_seconds = strtod(argv[++i], &end);
            if (*end != '\0' || !(spin_seconds >= 0.0 && spin_seconds <= 1.0)) {
                fprintf(stderr, "purity_server: --spin: give seconds from 0 to 1 (got %s)\n", argv[i]);
                return 2;
            }
        } else {
            fprintf(stderr, "usage: purity_server [--listen tcp:HOST:PORT | unix:PATH] [--once] [--spin SECONDS]\n");
            return 2;
        }
    }
    int server = listen_on(address);
    if (server < 0) {
        fprintf(stderr, "purity_server: cannot listen on %s: %s\n", address, strerror(errno));
        return 1;
    }
    do {
        int fd = accept(server, NULL, NULL);
        if (fd < 0) {
            if (errno == EINTR) continue;
            fprintf(stderr, "purity_server: accept: %s\n", strerror(errno));
            return 1;
        }
        int yes = 1;
        setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &yes, sizeof yes);     /* fails harmlessly on a Unix socket */
        serve_connection(fd);
        close(fd);
    } while (!once);
    close(server);
    return 0;
}
