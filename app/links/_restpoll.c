/* The poll thread's rounds for arms at rest, in C (issue 27; app/links/poller.py `_rest`).
 *
 * While every link the poll thread serves is armed and its last replies repeated (an arm at
 * rest), each of its samples is a request written at its slot and a reply that is byte for
 * byte the last one: nothing for Python to decide. `run` makes those rounds with the GIL let
 * go: at each link's slot it writes the link's request, waits (one `ppoll` over every link's
 * descriptor and the thread's wake-up pipe) for the reply, compares it with the expected
 * bytes and keeps only the time it was complete (CLOCK_REALTIME: Python's `time.time()`).
 * Over a socket that time is the kernel's (SO_TIMESTAMPNS: when its last bytes arrived), so
 * the thread need not be awake for the reply: once a reply has come with its time, the next
 * one is read at the link's following slot, just before that slot's request is written, and
 * the thread wakes once a period instead of twice (its slot, then the reply; most of an arm's
 * cost at rest is the wake-ups: docs/performance.md, "Session 36"). A reply not whole by then
 * is waited for as before, until its timeout; while the rounds stop (a pause, a batch due)
 * every reply in flight is waited for at once. A reply that comes without a time (a tty, a
 * Unix socket, or a TCP one before the kernel's worker has switched timestamps on for the
 * system, a moment after the first socket asks) is waited for and stamped when read.
 * It stops starting polls, lets the ones in flight end (whole, or at their timeout), and
 * returns when
 *   - a reply is not the expected one (another reading, short by its timeout, longer, or the
 *     port failed): it is handed back for Python's path (`ThreadLink.poll_ended`);
 *   - a link's batch is due (`until`, monotonic) or it holds `cap` repeats;
 *   - the wake-up pipe is written (a link added, paused, closing, its batch changed): it is
 *     drained here, as `PollThread._round` drains it.
 * The schedule is the Python round's (app/links/threaded.py `poll_ended`): a poll starts at
 * `slot - early` at the earliest; each one that ends moves its slot one period on, and a slot
 * more than `catch_up` periods behind skips ahead onto the period's grid. The bytes read are
 * read as `PollThread._read` reads them (up to `chunk` at a time; nothing where `poll` said
 * there was something is the peer's end; a reply in parts over a socket wakes the thread for
 * its first part and its rest: SO_RCVLOWAT); a request the port takes in parts is written as
 * `PollThread._write` writes it, within `write_wait` s.
 *
 *     run(links, wake_fd, early, catch_up, write_wait, chunk) -> list
 *
 * `links`: (fd, request, expect, timeout, slot, period, until, cap) each. Answers, for each
 * link in order, (slot, ats, end): its next slot, the times of the repeats it read (a list of
 * floats, in order), and how its last poll ended if not as a repeat: None, or ("reply", data,
 * deadline, at) (handed to Python as a `Reply`), or ("lost", reason).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <errno.h>
#include <math.h>
#include <poll.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/uio.h>
#include <time.h>
#include <unistd.h>

enum { END_NONE, END_REPLY, END_LOST };

typedef struct {
    int fd;
    char *req;
    Py_ssize_t req_len;
    char *expect;
    Py_ssize_t size;
    double timeout, slot, period, until;
    Py_ssize_t cap;
    /* the poll in flight */
    int flying;
    Py_ssize_t woff, got, bufcap;
    double deadline, write_by;
    int lowat; /* SO_RCVLOWAT set for the rest of a reply (-1: not a socket) */
    int timed;    /* the port is a socket with SO_TIMESTAMPNS on: read with `recvmsg` */
    int deferred; /* a reply came with the kernel's time: the next is read at its next slot */
    int watch;    /* the poll in flight is waited for (not deferred, or late at its slot) */
    double stamp; /* the kernel's time of the last bytes read of the poll in flight (0: none) */
    char *buf;
    /* what was read */
    double *ats;
    Py_ssize_t n;
    int end;
    double end_at, end_deadline;
    char reason[96];
} Rest;

static double clock_s(clockid_t id) {
    struct timespec t;
    clock_gettime(id, &t);
    return (double)t.tv_sec + (double)t.tv_nsec * 1e-9;
}

/* Have `poll` wake for socket `fd` only once `n` bytes are there (SO_RCVLOWAT), as
 * `PollThread._read` does for a reply that comes in parts (a Dynamixel bus's statuses): its
 * first part and its rest wake the thread, not each status. 0 where `fd` is no socket. */
static int set_lowat(int fd, int n) {
    return setsockopt(fd, SOL_SOCKET, SO_RCVLOWAT, &n, sizeof n) == 0;
}

static void lowat_off(Rest *r) {
    if (r->lowat == 1) {
        set_lowat(r->fd, 1);
        r->lowat = 0;
    }
}

static void lose(Rest *r, const char *why) {
    lowat_off(r);
    r->end = END_LOST;
    r->flying = 0;
    snprintf(r->reason, sizeof r->reason, "%s", why);
}

static void put(Rest *r) {
    while (r->woff < r->req_len) {
        ssize_t k = write(r->fd, r->req + r->woff, (size_t)(r->req_len - r->woff));
        if (k < 0) {
            if (errno == EINTR) continue;
            if (errno == EAGAIN || errno == EWOULDBLOCK) return;
            lose(r, strerror(errno));
            return;
        }
        r->woff += k;
    }
}

/* What the port has (`ready`: poll said it had something). */
static void take(Rest *r, int ready, Py_ssize_t chunk) {
    Py_ssize_t room = r->bufcap - r->got;
    if (room <= 0) return;
    if (room > chunk) room = chunk;
    ssize_t k;
    if (r->timed) {
        struct iovec iov = {r->buf + r->got, (size_t)room};
        union {
            char buf[CMSG_SPACE(sizeof(struct timespec))];
            struct cmsghdr align;
        } ctl;
        struct msghdr msg = {0};
        msg.msg_iov = &iov;
        msg.msg_iovlen = 1;
        msg.msg_control = ctl.buf;
        msg.msg_controllen = sizeof ctl.buf;
        do {
            k = recvmsg(r->fd, &msg, 0);
        } while (k < 0 && errno == EINTR);
        if (k > 0)
            for (struct cmsghdr *c = CMSG_FIRSTHDR(&msg); c != NULL; c = CMSG_NXTHDR(&msg, c))
                if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SCM_TIMESTAMPNS) {
                    struct timespec ts;
                    memcpy(&ts, CMSG_DATA(c), sizeof ts);
                    r->stamp = (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
                }
    } else {
        do {
            k = read(r->fd, r->buf + r->got, (size_t)room);
        } while (k < 0 && errno == EINTR);
    }
    if (k < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK) return;
        lose(r, strerror(errno));
        return;
    }
    if (k == 0) {
        if (ready) lose(r, "closed by the peer (end of file)");
        return;
    }
    r->got += k;
}

/* A slot this close to its period's grid is on it (`following`), s. */
#define GRID_TOL_S 1e-6

/* The slot a period after `slot`: on the period's grid (within GRID_TOL_S), the grid point
 * itself (one rounding), not a sum of periods that drifts off it by about one ulp a poll;
 * else `slot + period`. As app/links/poller.py `following`. */
static double following(double slot, double period) {
    double after = slot + period, on = floor(after / period + 0.5) * period;
    return fabs(on - after) < GRID_TOL_S ? on : after;
}

/* The poll in flight is over (whole, longer, or short at its deadline). */
static void done(Rest *r, double catch_up) {
    double at = clock_s(CLOCK_REALTIME), now = clock_s(CLOCK_MONOTONIC);
    if (r->stamp > 0) { /* the kernel's time: when the reply's last bytes came */
        if (r->stamp < at) at = r->stamp;
        r->deferred = 1;
    } else {
        r->deferred = 0;
    }
    r->flying = 0;
    lowat_off(r);
    if (r->got == r->size && memcmp(r->buf, r->expect, (size_t)r->size) == 0) {
        r->ats[r->n++] = at;
        r->slot = following(r->slot, r->period);
        if (r->slot < now - catch_up * r->period) /* far behind: onto the grid, ahead */
            r->slot = ceil((now + r->period - 1e-9) / r->period) * r->period;
        return;
    }
    r->end = END_REPLY;
    r->end_at = at;
    r->end_deadline = r->deadline;
}

static void run_rounds(Rest *rs, Py_ssize_t n, int wake_fd, double early, double catch_up,
                       double write_wait, Py_ssize_t chunk, struct pollfd *pfds, Rest **who) {
    int stopping = n == 0; /* (nothing to poll: back at once) */
    for (;;) {
        double now = clock_s(CLOCK_MONOTONIC);
        if (!stopping)
            for (Py_ssize_t i = 0; i < n; i++)
                if (rs[i].end != END_NONE || rs[i].n >= rs[i].cap || now >= rs[i].until)
                    stopping = 1;
        for (Py_ssize_t i = 0; i < n; i++) { /* replies read at the next slot, or now */
            Rest *r = &rs[i];
            if (!r->flying || r->watch || r->woff < r->req_len) continue;
            if (!stopping && following(r->slot, r->period) - early > now) continue;
            take(r, 0, chunk);
            if (r->end != END_NONE) {
                stopping = 1;
                continue;
            }
            if (r->got >= r->size) {
                done(r, catch_up); /* (then its `ats` may be full: no poll started after) */
                if (r->end != END_NONE || r->n >= r->cap) stopping = 1;
            } else { /* late: waited for, until its timeout */
                r->watch = 1;
                if (r->got > 0 && r->lowat != -1)
                    r->lowat = set_lowat(r->fd, (int)(r->size - r->got)) ? 1 : -1;
            }
        }
        if (!stopping)
            for (Py_ssize_t i = 0; i < n; i++) {
                Rest *r = &rs[i];
                if (r->flying || r->slot - early > now) continue;
                r->flying = 1;
                r->watch = !r->deferred;
                r->stamp = 0;
                r->woff = r->got = 0;
                r->deadline = now + r->timeout;
                r->write_by = now + write_wait;
                put(r);
                if (r->end != END_NONE) stopping = 1;
            }
        double wake_at = INFINITY;
        int nf = 1;
        pfds[0].fd = wake_fd;
        pfds[0].events = POLLIN;
        pfds[0].revents = 0;
        for (Py_ssize_t i = 0; i < n; i++) {
            Rest *r = &rs[i];
            if (r->flying) {
                if (r->deadline < wake_at) wake_at = r->deadline;
                short events = r->woff < r->req_len ? POLLOUT : 0;
                if (r->watch || stopping || events) {
                    events |= POLLIN;
                } else { /* its reply read at its next slot */
                    double read_at = following(r->slot, r->period) - early;
                    if (read_at < wake_at) wake_at = read_at;
                    continue;
                }
                pfds[nf].fd = r->fd;
                pfds[nf].events = events;
                pfds[nf].revents = 0;
                who[nf++] = r;
            } else if (!stopping && r->slot - early < wake_at) {
                wake_at = r->slot - early;
            }
        }
        if (stopping && nf == 1) return;
        struct timespec ts, *tsp = NULL;
        if (wake_at != INFINITY) {
            double left = wake_at - clock_s(CLOCK_MONOTONIC);
            if (left < 0) left = 0;
            ts.tv_sec = (time_t)left;
            ts.tv_nsec = (long)((left - (double)ts.tv_sec) * 1e9);
            tsp = &ts;
        }
        int got = ppoll(pfds, (nfds_t)nf, tsp, NULL);
        if (got < 0 && errno != EINTR) { /* (not seen): every poll in flight fails with it */
            const char *why = strerror(errno);
            for (int j = 1; j < nf; j++) lose(who[j], why);
            return;
        }
        if (got > 0) {
            if (pfds[0].revents) {
                char sink[512];
                while (read(wake_fd, sink, sizeof sink) > 0) {
                }
                stopping = 1;
            }
            for (int j = 1; j < nf; j++) {
                Rest *r = who[j];
                short ev = pfds[j].revents;
                if (!ev) continue;
                if ((ev & POLLOUT) && r->woff < r->req_len) put(r);
                if (r->end == END_NONE && (ev & (POLLIN | POLLERR | POLLHUP | POLLNVAL)))
                    take(r, 1, chunk);
                if (r->end == END_NONE && r->got >= r->size)
                    done(r, catch_up);
                else if (r->end == END_NONE && r->got > 0 && r->lowat != -1)
                    r->lowat = set_lowat(r->fd, (int)(r->size - r->got)) ? 1 : -1;
            }
        }
        now = clock_s(CLOCK_MONOTONIC);
        for (Py_ssize_t i = 0; i < n; i++) {
            Rest *r = &rs[i];
            if (!r->flying || now < r->deadline) continue;
            if (r->woff < r->req_len) {
                if (now >= r->write_by) {
                    char why[64];
                    snprintf(why, sizeof why, "the port took no bytes for %.0f s", write_wait);
                    lose(r, why);
                } else {
                    done(r, catch_up); /* short: the owner task resyncs */
                }
                continue;
            }
            /* what arrived by the time the thread looks counts (PollThread._round) */
            take(r, 0, chunk);
            if (r->end == END_NONE) done(r, catch_up);
        }
    }
}

static void free_rests(Rest *rs, Py_ssize_t n) {
    if (rs == NULL) return;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyMem_RawFree(rs[i].req);
        PyMem_RawFree(rs[i].expect);
        PyMem_RawFree(rs[i].buf);
        PyMem_RawFree(rs[i].ats);
    }
    PyMem_RawFree(rs);
}

static PyObject *result_of(Rest *r) {
    PyObject *ats = PyList_New(r->n);
    if (ats == NULL) return NULL;
    for (Py_ssize_t k = 0; k < r->n; k++) {
        PyObject *f = PyFloat_FromDouble(r->ats[k]);
        if (f == NULL) {
            Py_DECREF(ats);
            return NULL;
        }
        PyList_SET_ITEM(ats, k, f);
    }
    PyObject *end;
    if (r->end == END_REPLY)
        end = Py_BuildValue("(sy#dd)", "reply", r->buf, r->got, r->end_deadline, r->end_at);
    else if (r->end == END_LOST)
        end = Py_BuildValue("(ss)", "lost", r->reason);
    else
        end = Py_NewRef(Py_None);
    if (end == NULL) {
        Py_DECREF(ats);
        return NULL;
    }
    return Py_BuildValue("(dNN)", r->slot, ats, end);
}

static PyObject *run(PyObject *self, PyObject *args) {
    PyObject *links;
    int wake_fd;
    double early, catch_up, write_wait;
    Py_ssize_t chunk;
    (void)self;
    if (!PyArg_ParseTuple(args, "Oidddn", &links, &wake_fd, &early, &catch_up, &write_wait,
                          &chunk))
        return NULL;
    PyObject *seq = PySequence_Fast(links, "links must be a sequence");
    if (seq == NULL) return NULL;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(seq);
    if (chunk <= 0) chunk = 4096;
    Rest *rs = PyMem_RawCalloc((size_t)(n ? n : 1), sizeof(Rest));
    struct pollfd *pfds = PyMem_RawCalloc((size_t)n + 1, sizeof(struct pollfd));
    Rest **who = PyMem_RawCalloc((size_t)n + 1, sizeof(Rest *));
    PyObject *out = NULL;
    if (rs == NULL || pfds == NULL || who == NULL) {
        PyErr_NoMemory();
        goto finally;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        Rest *r = &rs[i];
        const char *req, *expect;
        Py_ssize_t req_len, size;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(seq, i), "iy#y#ddddn;a link",
                              &r->fd, &req, &req_len, &expect, &size, &r->timeout, &r->slot,
                              &r->period, &r->until, &r->cap))
            goto finally;
        if (size <= 0 || req_len <= 0 || r->period <= 0 || r->cap < 0) {
            PyErr_SetString(PyExc_ValueError, "a link's request, reply and period must not "
                                              "be empty");
            goto finally;
        }
        r->req = PyMem_RawMalloc((size_t)req_len);
        r->expect = PyMem_RawMalloc((size_t)size);
        r->bufcap = size + chunk;
        r->buf = PyMem_RawMalloc((size_t)r->bufcap);
        r->ats = PyMem_RawMalloc(sizeof(double) * (size_t)(r->cap ? r->cap : 1));
        if (!r->req || !r->expect || !r->buf || !r->ats) {
            PyErr_NoMemory();
            goto finally;
        }
        int on = 1; /* (a socket's replies carry the kernel's time; a tty's do not) */
        r->timed = setsockopt(r->fd, SOL_SOCKET, SO_TIMESTAMPNS, &on, sizeof on) == 0;
        r->watch = 1;
        memcpy(r->req, req, (size_t)req_len);
        memcpy(r->expect, expect, (size_t)size);
        r->req_len = req_len;
        r->size = size;
    }
    Py_BEGIN_ALLOW_THREADS
    run_rounds(rs, n, wake_fd, early, catch_up, write_wait, chunk, pfds, who);
    Py_END_ALLOW_THREADS
    out = PyList_New(n);
    if (out == NULL) goto finally;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *one = result_of(&rs[i]);
        if (one == NULL) {
            Py_CLEAR(out);
            goto finally;
        }
        PyList_SET_ITEM(out, i, one);
    }
finally:
    free_rests(rs, n);
    PyMem_RawFree(pfds);
    PyMem_RawFree(who);
    Py_DECREF(seq);
    return out;
}

static PyMethodDef methods[] = {
    {"run", run, METH_VARARGS,
     "run(links, wake_fd, early, catch_up, write_wait, chunk) -> [(slot, ats, end)]: the "
     "rounds of polls of links at rest, the GIL let go (module doc)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "_restpoll",
    .m_doc = "The poll thread's rounds for arms at rest, in C (app/links/_restpoll.c).",
    .m_size = -1,
    .m_methods = methods,
};

PyMODINIT_FUNC PyInit__restpoll(void) { return PyModule_Create(&module); }
