/*
 * _hubcore: the hub's data plane in C (bus.transports.hub._hubcore).
 *
 * What this module owns: reading the frame records of the hub's members, counting them, routing
 * them to the other members of their logical bus and writing them out, in one epoll loop, with
 * the same rules as the pure-Python path of bus/transports/hub/routing.py (that module's docstring
 * is the specification: forwarding, echo, classic-CAN members, acceptance filters, one send per
 * destination per round, bulk members held up to BULK_HOLD_S / BULK_MAX_BYTES (a gathering member
 * until a count of frames is held), a member that
 * stops reading dropped past MAX_OUTBUF_BYTES). The wire format is bus/transports/hub/wire.py's.
 *
 * Why C: profiling the rig (benchmarks/profile_rig.py, perf) showed the hub process spending
 * about two thirds of its CPU in the Python interpreter moving 24-byte records; this loop moves
 * them without it. Everything that is not the per-frame path stays in Python: accepting,
 * handshakes, stats queries, frame faults and bus time (a hub with either uses the Python path).
 *
 * The Python side (HubServer, bus/transports/hub/server.py and core.py) registers its own descriptors (listen sockets, wake pipe, clients
 * before their handshake) with watch(); poll() returns their events, and handles every member's
 * events itself. A member the core drops (disconnected, read/write error, output overflow, an
 * unknown record kind) is taken out of the core and reported by poll(); Python closes it.
 *
 * The member's side of the same wire, one function: answer_frames() (below Core), behind
 * HubBus.answer_frames (client.py): the receive loop of a drive's plain io ticks
 * (firmware_model/drive_node.py, DriveNode.step). It waits on the member's socket and one more
 * descriptor (the node's fieldbus), reads the records, hands each frame of a range of identifiers
 * and one length (the encoder frame of the drive's joint; the plant's four torque frames) to a
 * Python callable, which runs the tick, and writes the answers the callable returns (the torque
 * frame; the next tick's encoder frames); anything else goes back to the Python client, and the
 * loop returns. Why C: a drive spent about four fifths of its CPU per tick in the Python interpreter
 * around a control period of a few microseconds (benchmarks/robot_speed.py, py-spy; the numbers in
 * docs/benchmarks.md); the tick itself stays Python (the firmware's own code), only the waiting,
 * the reading and the record codec move here.
 *
 * A member's periodic frame without the interpreter: PeriodicWriter (below answer_frames), behind
 * HubBus.periodic_writer (client.py): a POSIX thread that writes one record every period on a
 * member of its own (nothing else sends there; its acceptance filter lets nothing in, and what
 * comes anyway, an error frame, is read and dropped) while its lease lasts, and keeps the longest
 * gap between two of its writes. Why C: the host's heartbeat (host/rig/host_heartbeat.py) must go
 * on while a law computes in the host's interpreter; a Python thread needs the GIL for every beat,
 * and a thread holding the GIL keeps it while the OS does not run it, so on a loaded machine a
 * beat came 505 ms late (the nodes' consumer time is 500 ms) with a pure-Python law running.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <errno.h>
#include <math.h>
#include <poll.h>
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#define HEADER_SIZE 24
#define STAMP_OFFSET 8
#define KIND_FRAME 1
#define KIND_FILTERS 2
#define KIND_RELEASE 3
#define KIND_GATHER 4
#define FLAG_EXT 0x01
#define FLAG_RTR 0x02
#define FLAG_ERR 0x04
#define FLAG_FD 0x08
#define FLAG_ECHO 0x40
#define FILTER_ENTRY_SIZE 9
#define MAX_EVENTS 64

/* what poll() reports for a descriptor */
#define REPORT_EVENTS 0 /* events of a descriptor Python watches */
#define REPORT_DROP 1   /* a member the core dropped: Python closes it */
#define REPORT_REFUSE 2 /* the same, and Python tells it why (ILNO) */

typedef struct {
    uint32_t id, mask;
    int8_t ext; /* -1 any, 0 standard, 1 extended */
} Filter;

typedef struct {
    uint8_t *p;
    size_t len, cap;
} Buf;

typedef struct Member {
    int fd, bus, echo, classic, bulk;
    Filter *filters;
    Py_ssize_t nfilters; /* 0: accept all */
    Buf in;              /* a partial record */
    Buf out;             /* unsent bytes (written when the socket is writable) */
    Buf pend;            /* routed this round; a bulk member's held frames */
    double held_since;   /* bulk / gather: monotonic s of the oldest held frame */
    uint32_t gather;     /* > 0: frames held until this many are (or BULK_HOLD_S passed) */
    uint32_t held_n;     /* records in pend */
    int queued;          /* on the round's destination list */
    int writing;         /* registered for EPOLLOUT */
    int dead;
    int refuse;
    char reason[96];
} Member;

typedef struct {
    long long frames, bits, bits_worst, fd_frames, error_frames, dropped_clients;
} Stats;

typedef struct {
    PyObject_HEAD
    int epfd;
    Member **members; /* by fd (NULL: not a member) */
    int members_cap;
    Member **round;   /* destinations with frames routed in this round */
    int round_len, round_cap;
    Member **dead;    /* dropped, not yet reported */
    int dead_len, dead_cap;
    Stats *stats;     /* by bus index */
    int nbus;
    unsigned short bits[2][9][2]; /* [extended][data bytes][nominal, worst case] */
    size_t recv_chunk, max_outbuf, bulk_max_bytes;
    double bulk_hold_s;
    uint8_t *rbuf;
} Core;

static double mono_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

static uint64_t wall_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

static int buf_reserve(Buf *b, size_t extra) {
    if (b->len + extra <= b->cap) return 0;
    size_t cap = b->cap ? b->cap : 256;
    while (cap < b->len + extra) cap *= 2;
    uint8_t *p = realloc(b->p, cap);
    if (!p) return -1;
    b->p = p;
    b->cap = cap;
    return 0;
}

static int buf_append(Buf *b, const uint8_t *data, size_t n) {
    if (buf_reserve(b, n) < 0) return -1;
    memcpy(b->p + b->len, data, n);
    b->len += n;
    return 0;
}

static void buf_consume(Buf *b, size_t n) {
    if (n >= b->len) {
        b->len = 0;
        return;
    }
    memmove(b->p, b->p + n, b->len - n);
    b->len -= n;
}

static void buf_free(Buf *b) {
    free(b->p);
    b->p = NULL;
    b->len = b->cap = 0;
}

static uint32_t u32le(const uint8_t *p) {
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static void put_u64le(uint8_t *p, uint64_t v) {
    for (int i = 0; i < 8; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static int accepts(const Member *m, uint32_t can_id, int ext) {
    if (m->nfilters == 0) return 1;
    for (Py_ssize_t i = 0; i < m->nfilters; i++) {
        const Filter *f = &m->filters[i];
        if (f->ext >= 0 && f->ext != ext) continue;
        if (((f->id ^ can_id) & f->mask) == 0) return 1;
    }
    return 0;
}

static void kill_member(Core *c, Member *m, const char *reason, int refuse) {
    if (m->dead) return;
    m->dead = 1;
    m->refuse = refuse;
    snprintf(m->reason, sizeof m->reason, "%s", reason);
    epoll_ctl(c->epfd, EPOLL_CTL_DEL, m->fd, NULL);
    if (c->dead_len == c->dead_cap) {
        int cap = c->dead_cap ? 2 * c->dead_cap : 8;
        Member **p = realloc(c->dead, (size_t)cap * sizeof *p);
        if (!p) return; /* reported as lost memory; the member stays dead */
        c->dead = p;
        c->dead_cap = cap;
    }
    c->dead[c->dead_len++] = m;
}

static void set_events(Core *c, Member *m) {
    struct epoll_event ev = {0};
    ev.events = EPOLLIN | (m->writing ? EPOLLOUT : 0);
    ev.data.fd = m->fd;
    epoll_ctl(c->epfd, EPOLL_CTL_MOD, m->fd, &ev);
}

/* one send of data, the rest queued (as HubServer._send_to) */
static void send_to(Core *c, Member *m, const uint8_t *data, size_t n) {
    if (m->dead || !n) return;
    if (m->out.len == 0) {
        ssize_t sent = send(m->fd, data, n, MSG_DONTWAIT | MSG_NOSIGNAL);
        if (sent < 0) {
            if (errno != EAGAIN && errno != EWOULDBLOCK) {
                char text[80];
                snprintf(text, sizeof text, "send error %s", strerror(errno));
                kill_member(c, m, text, 0);
                return;
            }
            sent = 0;
        }
        if ((size_t)sent == n) return;
        data += sent;
        n -= (size_t)sent;
    }
    if (buf_append(&m->out, data, n) < 0 || m->out.len > c->max_outbuf) {
        c->stats[m->bus].dropped_clients++;
        kill_member(c, m, "output buffer overflow", 0);
        return;
    }
    if (!m->writing) {
        m->writing = 1;
        set_events(c, m);
    }
}

static void flush_out(Core *c, Member *m) {
    ssize_t sent = send(m->fd, m->out.p, m->out.len, MSG_DONTWAIT | MSG_NOSIGNAL);
    if (sent < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK) return;
        char text[80];
        snprintf(text, sizeof text, "send error %s", strerror(errno));
        kill_member(c, m, text, 0);
        return;
    }
    buf_consume(&m->out, (size_t)sent);
    if (m->out.len == 0 && m->writing) {
        m->writing = 0;
        set_events(c, m);
    }
}

static void queue_for(Core *c, Member *m, const uint8_t *rec, size_t n, int echo) {
    if (buf_append(&m->pend, rec, n) < 0) {
        kill_member(c, m, "out of memory", 0);
        return;
    }
    if (echo) m->pend.p[m->pend.len - n + 1] |= FLAG_ECHO;
    m->held_n++;
    if (!m->queued) {
        if (c->round_len == c->round_cap) {
            int cap = c->round_cap ? 2 * c->round_cap : 16;
            Member **p = realloc(c->round, (size_t)cap * sizeof *p);
            if (!p) {
                kill_member(c, m, "out of memory", 0);
                return;
            }
            c->round = p;
            c->round_cap = cap;
        }
        m->queued = 1;
        c->round[c->round_len++] = m;
    }
}

static void route_frame(Core *c, Member *sender, const uint8_t *rec, size_t total) {
    uint8_t flags = rec[1];
    uint8_t length = rec[3];
    uint32_t can_id = u32le(rec + 4);
    int ext = (flags & FLAG_EXT) ? 1 : 0;
    int fd = flags & FLAG_FD;
    /* a bus error frame reaches every member whatever its acceptance filters (SocketCAN delivers
       error frames by the socket's error mask, which python-can's SocketcanBus opens to all) */
    int err = flags & FLAG_ERR;
    Stats *st = &c->stats[sender->bus];
    if (err) {
        st->error_frames++;
    } else if (fd) {
        st->fd_frames++;
    } else {
        int n = (flags & FLAG_RTR) ? 0 : (length < 8 ? length : 8);
        st->frames++;
        st->bits += c->bits[ext][n][0];
        st->bits_worst += c->bits[ext][n][1];
    }
    /* members in join order (the order of the fd table is not the join order, but the order of
       destinations never matters: each destination's frames keep their order) */
    for (int i = 0; i < c->members_cap; i++) {
        Member *m = c->members[i];
        if (!m || m->dead || m->bus != sender->bus) continue;
        if (fd && m->classic) continue;
        if (m == sender) {
            if (m->echo && (err || accepts(m, can_id, ext))) queue_for(c, m, rec, total, 1);
        } else if (err || accepts(m, can_id, ext)) {
            queue_for(c, m, rec, total, 0);
        }
    }
}

static void release_held(Core *c, Member *m);

/* every whole record of m->in (stamped with stamp_ns) */
static void parse_input(Core *c, Member *m, uint64_t stamp_ns) {
    Buf *b = &m->in;
    size_t off = 0;
    while (!m->dead && b->len - off >= HEADER_SIZE) {
        uint8_t *rec = b->p + off;
        uint8_t kind = rec[0];
        size_t total;
        if (kind == KIND_FRAME) {
            uint8_t length = rec[3];
            total = HEADER_SIZE + (length > 8 ? (size_t)length - 8 : 0);
            if (b->len - off < total) break;
            put_u64le(rec + STAMP_OFFSET, stamp_ns);
            route_frame(c, m, rec, total);
        } else if (kind == KIND_FILTERS) {
            size_t n = u32le(rec + 4);
            total = HEADER_SIZE + n;
            if (b->len - off < total) break;
            Py_ssize_t count = (Py_ssize_t)(n / FILTER_ENTRY_SIZE);
            Filter *fs = NULL;
            if (count) {
                fs = malloc((size_t)count * sizeof *fs);
                if (!fs) {
                    kill_member(c, m, "out of memory", 0);
                    break;
                }
                for (Py_ssize_t i = 0; i < count; i++) {
                    const uint8_t *e = rec + HEADER_SIZE + (size_t)i * FILTER_ENTRY_SIZE;
                    fs[i].id = u32le(e);
                    fs[i].mask = u32le(e + 4);
                    fs[i].ext = (int8_t)e[8];
                }
            }
            free(m->filters);
            m->filters = fs;
            m->nfilters = count;
        } else if (kind == KIND_GATHER) {
            /* deliver this member's frames once this many are routed to it (0: at once again) */
            total = HEADER_SIZE;
            m->gather = u32le(rec + 4);
            if (m->pend.len && (!m->gather || m->held_n >= m->gather)) release_held(c, m);
        } else if (kind == KIND_RELEASE) {
            /* a bulk member asks for what is held for it (and this round routed to it) now */
            total = HEADER_SIZE;
            if (m->bulk && m->pend.len) release_held(c, m);
        } else {
            char text[48];
            snprintf(text, sizeof text, "unknown record kind %u", kind);
            kill_member(c, m, text, 1);
            break;
        }
        off += total;
    }
    buf_consume(b, off);
}

static void on_readable(Core *c, Member *m) {
    ssize_t n = recv(m->fd, c->rbuf, c->recv_chunk, MSG_DONTWAIT);
    if (n < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) return;
        char text[80];
        snprintf(text, sizeof text, "recv error %s", strerror(errno));
        kill_member(c, m, text, 0);
        return;
    }
    uint64_t stamp = wall_ns(); /* the receive time of every frame completed by this read */
    if (n == 0) {
        kill_member(c, m, "disconnected", 0);
        return;
    }
    if (buf_append(&m->in, c->rbuf, (size_t)n) < 0) {
        kill_member(c, m, "out of memory", 0);
        return;
    }
    parse_input(c, m, stamp);
}

static void release_held(Core *c, Member *m) {
    size_t n = m->pend.len;
    m->pend.len = 0;
    m->held_n = 0;
    m->held_since = 0.0;
    send_to(c, m, m->pend.p, n);
}

/* one send per destination of what this round routed; a bulk member's frames are held */
static void send_round(Core *c) {
    for (int i = 0; i < c->round_len; i++) {
        Member *m = c->round[i];
        m->queued = 0;
        if (m->dead) continue;
        if (m->bulk || m->gather) {
            if (!m->pend.len) continue; /* released by its own request this round */
            if (m->held_since == 0.0) m->held_since = mono_s();
            if (m->pend.len >= c->bulk_max_bytes || (m->gather && m->held_n >= m->gather)) release_held(c, m);
        } else {
            size_t n = m->pend.len;
            m->pend.len = 0;
            m->held_n = 0;
            send_to(c, m, m->pend.p, n);
        }
    }
    c->round_len = 0;
}

static void free_member(Member *m) {
    buf_free(&m->in);
    buf_free(&m->out);
    buf_free(&m->pend);
    free(m->filters);
    free(m);
}

/* ---------------------------------------------------------------- Python type */

static void Core_dealloc(Core *c) {
    for (int i = 0; i < c->members_cap; i++)
        if (c->members[i] && !c->members[i]->dead) free_member(c->members[i]);
    for (int i = 0; i < c->dead_len; i++) free_member(c->dead[i]);
    free(c->members);
    free(c->round);
    free(c->dead);
    free(c->stats);
    free(c->rbuf);
    if (c->epfd >= 0) close(c->epfd);
    Py_TYPE(c)->tp_free((PyObject *)c);
}

static int Core_init(Core *c, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"bits", "recv_chunk", "max_outbuf", "bulk_hold_s", "bulk_max_bytes", NULL};
    PyObject *bits;
    Py_ssize_t recv_chunk, max_outbuf, bulk_max;
    double hold;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "Onndn", kwlist, &bits, &recv_chunk, &max_outbuf, &hold, &bulk_max))
        return -1;
    PyObject *seq = PySequence_Fast(bits, "bits must be a sequence of 36 ints");
    if (!seq) return -1;
    if (PySequence_Fast_GET_SIZE(seq) != 36) {
        Py_DECREF(seq);
        PyErr_SetString(PyExc_ValueError, "bits must hold 36 ints: [extended][data bytes 0..8][nominal, worst case]");
        return -1;
    }
    for (int i = 0; i < 36; i++) {
        long v = PyLong_AsLong(PySequence_Fast_GET_ITEM(seq, i));
        if (v == -1 && PyErr_Occurred()) {
            Py_DECREF(seq);
            return -1;
        }
        c->bits[i / 18][(i / 2) % 9][i % 2] = (unsigned short)v;
    }
    Py_DECREF(seq);
    if (recv_chunk <= 0 || max_outbuf <= 0 || bulk_max <= 0 || hold < 0) {
        PyErr_SetString(PyExc_ValueError, "sizes must be > 0 and the hold time >= 0");
        return -1;
    }
    c->recv_chunk = (size_t)recv_chunk;
    c->max_outbuf = (size_t)max_outbuf;
    c->bulk_hold_s = hold;
    c->bulk_max_bytes = (size_t)bulk_max;
    c->rbuf = malloc(c->recv_chunk);
    c->epfd = epoll_create1(EPOLL_CLOEXEC);
    if (!c->rbuf || c->epfd < 0) {
        PyErr_SetFromErrno(PyExc_OSError);
        return -1;
    }
    return 0;
}

static PyObject *Core_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    Core *c = (Core *)type->tp_alloc(type, 0);
    if (c) c->epfd = -1;
    return (PyObject *)c;
}

static int ensure_bus(Core *c, int bus) {
    if (bus < c->nbus) return 0;
    Stats *s = realloc(c->stats, (size_t)(bus + 1) * sizeof *s);
    if (!s) return -1;
    memset(s + c->nbus, 0, (size_t)(bus + 1 - c->nbus) * sizeof *s);
    c->stats = s;
    c->nbus = bus + 1;
    return 0;
}

static PyObject *Core_watch(Core *c, PyObject *args) {
    int fd;
    unsigned int events;
    if (!PyArg_ParseTuple(args, "iI", &fd, &events)) return NULL;
    struct epoll_event ev = {0};
    ev.events = events;
    ev.data.fd = fd;
    if (epoll_ctl(c->epfd, EPOLL_CTL_MOD, fd, &ev) < 0) {
        if (errno != ENOENT || epoll_ctl(c->epfd, EPOLL_CTL_ADD, fd, &ev) < 0) return PyErr_SetFromErrno(PyExc_OSError);
    }
    Py_RETURN_NONE;
}

static PyObject *Core_unwatch(Core *c, PyObject *args) {
    int fd;
    if (!PyArg_ParseTuple(args, "i", &fd)) return NULL;
    if (fd >= 0 && fd < c->members_cap && c->members[fd]) {
        PyErr_Format(PyExc_ValueError, "descriptor %d is a member (use remove)", fd);
        return NULL;
    }
    epoll_ctl(c->epfd, EPOLL_CTL_DEL, fd, NULL);
    Py_RETURN_NONE;
}

static PyObject *Core_add_member(Core *c, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"fd", "bus", "echo", "classic", "bulk", "inbuf", "outbuf", "stamp_ns", NULL};
    int fd, bus, echo, classic, bulk;
    unsigned long long stamp_ns;
    Py_buffer in = {0}, out = {0};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "iipppy*y*K", kwlist, &fd, &bus, &echo, &classic, &bulk, &in, &out,
                                     &stamp_ns))
        return NULL;
    PyObject *result = NULL;
    Member *m = NULL;
    if (fd < 0 || bus < 0) {
        PyErr_SetString(PyExc_ValueError, "fd and bus must be >= 0");
        goto done;
    }
    if (fd < c->members_cap && c->members[fd]) {
        PyErr_Format(PyExc_ValueError, "descriptor %d is a member already", fd);
        goto done;
    }
    if (ensure_bus(c, bus) < 0) {
        PyErr_NoMemory();
        goto done;
    }
    if (fd >= c->members_cap) {
        int cap = c->members_cap ? c->members_cap : 64;
        while (cap <= fd) cap *= 2;
        Member **p = realloc(c->members, (size_t)cap * sizeof *p);
        if (!p) {
            PyErr_NoMemory();
            goto done;
        }
        memset(p + c->members_cap, 0, (size_t)(cap - c->members_cap) * sizeof *p);
        c->members = p;
        c->members_cap = cap;
    }
    m = calloc(1, sizeof *m);
    if (!m) {
        PyErr_NoMemory();
        goto done;
    }
    m->fd = fd;
    m->bus = bus;
    m->echo = echo;
    m->classic = classic;
    m->bulk = bulk;
    struct epoll_event ev = {0};
    ev.events = EPOLLIN;
    ev.data.fd = fd;
    epoll_ctl(c->epfd, EPOLL_CTL_DEL, fd, NULL); /* Python may have watched it during the handshake */
    if (epoll_ctl(c->epfd, EPOLL_CTL_ADD, fd, &ev) < 0) {
        PyErr_SetFromErrno(PyExc_OSError);
        free(m);
        goto done;
    }
    c->members[fd] = m;
    if (out.len) send_to(c, m, out.buf, (size_t)out.len);
    if (in.len && !m->dead) {
        if (buf_append(&m->in, in.buf, (size_t)in.len) < 0)
            kill_member(c, m, "out of memory", 0);
        else
            parse_input(c, m, (uint64_t)stamp_ns); /* sent with the next round */
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&in);
    PyBuffer_Release(&out);
    return result;
}

static void forget(Core *c, Member *m) {
    if (m->fd < c->members_cap && c->members[m->fd] == m) c->members[m->fd] = NULL;
    for (int i = 0; i < c->round_len; i++)
        if (c->round[i] == m) {
            c->round[i] = c->round[--c->round_len];
            break;
        }
}

static PyObject *Core_remove(Core *c, PyObject *args) {
    int fd;
    if (!PyArg_ParseTuple(args, "i", &fd)) return NULL;
    if (fd >= 0 && fd < c->members_cap && c->members[fd]) {
        Member *m = c->members[fd];
        forget(c, m);
        if (m->dead) {
            for (int i = 0; i < c->dead_len; i++)
                if (c->dead[i] == m) {
                    c->dead[i] = c->dead[--c->dead_len];
                    break;
                }
        } else {
            epoll_ctl(c->epfd, EPOLL_CTL_DEL, fd, NULL);
        }
        free_member(m);
    }
    Py_RETURN_NONE;
}

/* reports of the dropped members: (fd, REPORT_DROP / REPORT_REFUSE, reason) */
static int report_dead(Core *c, PyObject *list) {
    for (int i = 0; i < c->dead_len; i++) {
        Member *m = c->dead[i];
        PyObject *t = Py_BuildValue("iis", m->fd, m->refuse ? REPORT_REFUSE : REPORT_DROP, m->reason);
        if (!t || PyList_Append(list, t) < 0) {
            Py_XDECREF(t);
            return -1;
        }
        Py_DECREF(t);
        forget(c, m);
        free_member(m);
    }
    c->dead_len = 0;
    return 0;
}

static void release_due(Core *c, double now) {
    for (int i = 0; i < c->members_cap; i++) {
        Member *m = c->members[i];
        if (m && !m->dead && (m->bulk || m->gather) && m->held_since != 0.0 && now - m->held_since >= c->bulk_hold_s)
            release_held(c, m);
    }
}

static PyObject *Core_poll(Core *c, PyObject *args) {
    double timeout_s;
    if (!PyArg_ParseTuple(args, "d", &timeout_s)) return NULL;
    send_round(c); /* what add_member routed */
    double now = mono_s();
    release_due(c, now);
    /* the next bulk release bounds the wait */
    for (int i = 0; i < c->members_cap; i++) {
        Member *m = c->members[i];
        if (m && !m->dead && (m->bulk || m->gather) && m->held_since != 0.0) {
            double due = m->held_since + c->bulk_hold_s - now;
            if (timeout_s < 0 || due < timeout_s) timeout_s = due < 0 ? 0 : due;
        }
    }
    PyObject *list = PyList_New(0);
    if (!list) return NULL;
    if (c->dead_len) {
        if (report_dead(c, list) < 0) goto fail;
        return list;
    }
    /* whole milliseconds, rounded up (as Python's EpollSelector); a day at most (no int overflow) */
    int timeout_ms = timeout_s < 0 ? -1 : timeout_s > 86400.0 ? 86400000 : (int)(timeout_s * 1e3 + 0.999999);
    struct epoll_event events[MAX_EVENTS];
    int n;
    Py_BEGIN_ALLOW_THREADS
    n = epoll_wait(c->epfd, events, MAX_EVENTS, timeout_ms);
    Py_END_ALLOW_THREADS
    if (n < 0) {
        if (errno == EINTR) { /* let Python run its signal handlers; the caller polls again */
            if (PyErr_CheckSignals() < 0) goto fail;
            return list;
        }
        PyErr_SetFromErrno(PyExc_OSError);
        goto fail;
    }
    for (int i = 0; i < n; i++) {
        int fd = events[i].data.fd;
        uint32_t ev = events[i].events;
        Member *m = fd < c->members_cap ? c->members[fd] : NULL;
        if (m) {
            if (m->dead) continue;
            if (ev & (EPOLLIN | EPOLLHUP | EPOLLERR)) on_readable(c, m);
            if (!m->dead && (ev & EPOLLOUT) && m->out.len) flush_out(c, m);
        } else {
            PyObject *t = Py_BuildValue("iik", fd, REPORT_EVENTS, (unsigned long)ev);
            if (!t) goto fail;
            if (PyList_Append(list, t) < 0) {
                Py_DECREF(t);
                goto fail;
            }
            Py_DECREF(t);
        }
    }
    send_round(c);
    release_due(c, mono_s());
    if (report_dead(c, list) < 0) goto fail;
    return list;
fail:
    Py_DECREF(list);
    return NULL;
}

static PyObject *Core_stats(Core *c, PyObject *args) {
    int bus, reset = 0;
    if (!PyArg_ParseTuple(args, "i|p", &bus, &reset)) return NULL;
    if (bus < 0) {
        PyErr_SetString(PyExc_ValueError, "bus must be >= 0");
        return NULL;
    }
    if (bus >= c->nbus) return Py_BuildValue("(LLLLLL)", 0LL, 0LL, 0LL, 0LL, 0LL, 0LL);
    Stats *s = &c->stats[bus];
    PyObject *t = Py_BuildValue("(LLLLLL)", s->frames, s->bits, s->bits_worst, s->fd_frames, s->error_frames,
                                s->dropped_clients);
    if (t && reset) s->frames = s->bits = s->bits_worst = s->fd_frames = s->error_frames = 0;
    return t;
}

static PyObject *Core_close(Core *c, PyObject *Py_UNUSED(ignored)) {
    if (c->epfd >= 0) {
        close(c->epfd);
        c->epfd = -1;
    }
    Py_RETURN_NONE;
}

static PyMethodDef Core_methods[] = {
    {"watch", (PyCFunction)Core_watch, METH_VARARGS,
     "watch(fd, events): report the epoll events of a descriptor Python handles (set or change)"},
    {"unwatch", (PyCFunction)Core_unwatch, METH_VARARGS, "unwatch(fd): stop reporting a descriptor"},
    {"add_member", (PyCFunction)(void (*)(void))Core_add_member, METH_VARARGS | METH_KEYWORDS,
     "add_member(fd, bus, echo, classic, bulk, inbuf, outbuf, stamp_ns): the core reads, routes and writes "
     "this member from now on (inbuf: bytes read after its handshake, received at stamp_ns; outbuf: bytes "
     "still to send to it)"},
    {"remove", (PyCFunction)Core_remove, METH_VARARGS, "remove(fd): forget a member (Python closes it)"},
    {"poll", (PyCFunction)Core_poll, METH_VARARGS,
     "poll(timeout_s) -> [(fd, kind, value)]: wait (timeout_s < 0: no limit) and serve the members; kind 0: "
     "events of a watched descriptor (value: the epoll mask), 1: a member dropped (value: why), 2: a member "
     "refused (value: why; Python tells it)"},
    {"stats", (PyCFunction)Core_stats, METH_VARARGS,
     "stats(bus, reset=False) -> (frames, bits, bits_worst_case, fd_frames, error_frames, dropped_clients)"},
    {"close", (PyCFunction)Core_close, METH_NOARGS, "close the epoll descriptor"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject CoreType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "bus.transports.hub._hubcore.Core",
    .tp_basicsize = sizeof(Core),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "The hub's data plane: members' frames read, counted, routed and written in C.",
    .tp_new = Core_new,
    .tp_init = (initproc)Core_init,
    .tp_dealloc = (destructor)Core_dealloc,
    .tp_methods = Core_methods,
};

/* ---------------------------------------------------------------- answer_frames (a member's side) */

#define BURST_TIMEOUT 0 /* the deadline came, or a signal interrupted the wait (its handler ran) */
#define BURST_OTHER 1   /* the other descriptor is readable (the drive's fieldbus first) */
#define BURST_PYTHON 2  /* a record that is not a plain encoder frame: in rest, for Python */
#define BURST_STOPPED 3 /* the callable returned None: it handled its tick itself */
#define BURST_CLOSED 4  /* the io socket read 0 bytes or failed: Python's own read says why */
#define BURST_SENDFAIL 5 /* writing the torque frame failed (errno in the result) */
#define BURST_CHUNK 65536
#define MAX_ANSWERS 16 /* answers to one frame, written in one send */

static int set_rest(PyObject *rest, const uint8_t *p, size_t n) {
    if (PyByteArray_Resize(rest, (Py_ssize_t)n) < 0) return -1;
    if (n) memcpy(PyByteArray_AS_STRING(rest), p, n);
    return 0;
}

/* write all of rec[0..n) to a blocking (or non-blocking) stream socket; 0, or the errno */
static int send_all(int fd, const uint8_t *rec, size_t n) {
    size_t off = 0;
    while (off < n) {
        ssize_t k = send(fd, rec + off, n - off, MSG_NOSIGNAL);
        if (k > 0) {
            off += (size_t)k;
            continue;
        }
        if (k < 0 && errno == EINTR) continue;
        if (k < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            struct pollfd p = {.fd = fd, .events = POLLOUT};
            if (poll(&p, 1, -1) < 0 && errno != EINTR) return errno;
            continue;
        }
        return k < 0 ? errno : EPIPE;
    }
    return 0;
}

static PyObject *answer_frames(PyObject *self, PyObject *args) {
    int io_fd, other_fd;
    double deadline_s;
    unsigned int rx_id, rx_count, rx_len;
    PyObject *on_frame, *rest, *lock;
    if (!PyArg_ParseTuple(args, "iidIIIOO!O:answer_frames", &io_fd, &other_fd, &deadline_s, &rx_id, &rx_count, &rx_len,
                          &on_frame, &PyByteArray_Type, &rest, &lock))
        return NULL;
    if (rx_len > 8 || rx_id > 0x7FF || rx_count > 0x800 - rx_id) {
        PyErr_SetString(PyExc_ValueError, "answer_frames: classic frames (rx_len <= 8, rx_id + rx_count <= 0x800)");
        return NULL;
    }
    if (isnan(deadline_s)) {
        PyErr_SetString(PyExc_ValueError, "answer_frames: the deadline is not a number");
        return NULL;
    }
    uint8_t *buf = malloc(BURST_CHUNK);
    if (!buf) return PyErr_NoMemory();
    size_t len = 0;      /* bytes in buf (records not yet handled, a partial one at the end) */
    long ticks = 0;      /* ticks run */
    int why = BURST_TIMEOUT, err = 0;
    for (;;) {
        size_t off = 0;
        while (len - off >= HEADER_SIZE) {
            const uint8_t *rec = buf + off;
            uint32_t index = u32le(rec + 4) - rx_id; /* wraps for an id below rx_id */
            if (rec[0] != KIND_FRAME || rec[1] != 0 || rec[2] != rx_len || rec[3] != rx_len || index >= rx_count) {
                why = BURST_PYTHON;
                goto done;
            }
            off += HEADER_SIZE;
            ticks++;
            PyObject *res = PyObject_CallFunction(on_frame, "Iy#", (unsigned)index, (const char *)rec + 16, (Py_ssize_t)rx_len);
            if (!res) {
                set_rest(rest, buf + off, len - off);
                free(buf);
                return NULL;
            }
            if (res == Py_None) {
                Py_DECREF(res);
                why = BURST_STOPPED;
                goto done;
            }
            uint8_t out[HEADER_SIZE * MAX_ANSWERS];
            size_t nout = 0;
            PyObject *seq = PySequence_Fast(res, "answer_frames: the answers must be a sequence of (id, data) pairs or None");
            Py_DECREF(res);
            if (seq && PySequence_Fast_GET_SIZE(seq) > MAX_ANSWERS) {
                PyErr_SetString(PyExc_ValueError, "answer_frames: more than 16 answers to one frame");
                Py_CLEAR(seq);
            }
            for (Py_ssize_t a = 0; seq && a < PySequence_Fast_GET_SIZE(seq); a++) {
                unsigned int tx_id;
                const char *data;
                Py_ssize_t n;
                PyObject *pair = PySequence_Fast_GET_ITEM(seq, a);
                if (!PyArg_ParseTuple(pair, "Iy#:answer", &tx_id, &data, &n)) {
                    Py_CLEAR(seq);
                } else if (tx_id > 0x7FF || n > 8) {
                    PyErr_Format(PyExc_ValueError, "answer_frames: not a classic data frame: 0x%X, %zd bytes", tx_id, n);
                    Py_CLEAR(seq);
                } else {
                    uint8_t *o = out + nout;
                    memset(o, 0, HEADER_SIZE);
                    o[0] = KIND_FRAME;
                    o[2] = o[3] = (uint8_t)n;
                    o[4] = (uint8_t)tx_id;
                    o[5] = (uint8_t)(tx_id >> 8);
                    memcpy(o + 16, data, (size_t)n);
                    nout += HEADER_SIZE;
                }
            }
            if (!seq) {
                set_rest(rest, buf + off, len - off);
                free(buf);
                return NULL;
            }
            Py_DECREF(seq);
            if (!nout) continue;
            PyObject *held = PyObject_CallMethod(lock, "acquire", NULL); /* the client's send lock */
            if (!held) {
                set_rest(rest, buf + off, len - off);
                free(buf);
                return NULL;
            }
            Py_DECREF(held);
            err = send_all(io_fd, out, nout);
            PyObject *freed = PyObject_CallMethod(lock, "release", NULL);
            if (!freed) {
                set_rest(rest, buf + off, len - off);
                free(buf);
                return NULL;
            }
            Py_DECREF(freed);
            if (err) {
                why = BURST_SENDFAIL;
                goto done;
            }
        }
        if (off) {
            memmove(buf, buf + off, len - off);
            len -= off;
        }
        struct pollfd fds[2] = {{.fd = io_fd, .events = POLLIN}, {.fd = other_fd, .events = POLLIN}};
        double left = deadline_s - mono_s();
        if (left <= 0) {
            why = BURST_TIMEOUT;
            goto done_at;
        }
        if (left > 86400.0) left = 86400.0; /* a far (or infinite) deadline: a day's wait at a time */
        struct timespec ts = {.tv_sec = (time_t)left, .tv_nsec = (long)((left - (double)(time_t)left) * 1e9)};
        int r;
        Py_BEGIN_ALLOW_THREADS r = ppoll(fds, other_fd >= 0 ? 2 : 1, &ts, NULL);
        Py_END_ALLOW_THREADS if (r < 0) {
            if (errno == EINTR) { /* a signal: its Python handler runs now, and the caller looks (a stop event) */
                if (PyErr_CheckSignals() < 0) {
                    set_rest(rest, buf, len);
                    free(buf);
                    return NULL;
                }
                why = BURST_TIMEOUT;
                goto done_at;
            }
            why = BURST_CLOSED;
            goto done_at;
        }
        if (r == 0) continue; /* the deadline: checked above */
        if (other_fd >= 0 && fds[1].revents) {
            why = BURST_OTHER;
            goto done_at;
        }
        if (!fds[0].revents) continue;
        if (fds[0].revents & ~POLLIN) { /* hang-up or error: Python's read reports it */
            why = BURST_CLOSED;
            goto done_at;
        }
        ssize_t k = recv(io_fd, buf + len, BURST_CHUNK - len, MSG_DONTWAIT);
        if (k < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) continue;
        if (k <= 0) {
            why = BURST_CLOSED;
            goto done_at;
        }
        len += (size_t)k;
        continue;
    done:
        memmove(buf, buf + off, len - off);
        len -= off;
    done_at:
        break;
    }
    if (set_rest(rest, buf, len) < 0) {
        free(buf);
        return NULL;
    }
    free(buf);
    return Py_BuildValue("lii", ticks, why, err);
}

/* ---------------------------------------------------------------- PeriodicWriter (a member's beat) */

typedef struct {
    PyObject_HEAD
    pthread_mutex_t mu;
    pthread_cond_t cv;
    pthread_t thread;
    int started, joined, stop;
    int starved; /* the last period passed without a write: the lease had run out */
    int kick;    /* a lease came after that: write now, not at the next period */
    int fd;
    uint8_t rec[HEADER_SIZE + 64];
    size_t rec_len;
    double period_s;
    double lease_until; /* CLOCK_MONOTONIC s: no write after it (INFINITY: no lease) */
    long long sent;
    double last_sent;   /* -1: none yet */
    double gap_s, gap_end; /* the longest gap between two writes not taken yet (gap_s < 0: none) */
    int err;            /* errno of the write (or read) that ended the thread, 0 */
    double err_t;
} PeriodicWriter;

static void abs_time(double t_s, struct timespec *ts) {
    double sec = floor(t_s);
    ts->tv_sec = (time_t)sec;
    ts->tv_nsec = (long)((t_s - sec) * 1e9);
    if (ts->tv_nsec >= 1000000000L) {
        ts->tv_sec += 1;
        ts->tv_nsec -= 1000000000L;
    }
}

/* what came on the member (its filter lets nothing in but error frames): read and dropped; 0, or the
 * errno (EPIPE: the hub closed the connection) */
static int drain(int fd) {
    uint8_t buf[4096];
    for (;;) {
        ssize_t k = recv(fd, buf, sizeof buf, MSG_DONTWAIT);
        if (k > 0) continue;
        if (k == 0) return EPIPE;
        if (errno == EINTR) continue;
        if (errno == EAGAIN || errno == EWOULDBLOCK) return 0;
        return errno;
    }
}

static void *writer_main(void *arg) {
    PeriodicWriter *w = (PeriodicWriter *)arg;
    pthread_mutex_lock(&w->mu);
    double due = mono_s();
    while (!w->stop) {
        w->starved = mono_s() > w->lease_until;
        if (!w->starved) {
            pthread_mutex_unlock(&w->mu);
            int e = send_all(w->fd, w->rec, w->rec_len);
            if (!e) e = drain(w->fd);
            double t = mono_s();
            pthread_mutex_lock(&w->mu);
            if (e) {
                w->err = e;
                w->err_t = t;
                break;
            }
            w->sent++;
            if (w->last_sent >= 0 && t - w->last_sent > w->gap_s) {
                w->gap_s = t - w->last_sent;
                w->gap_end = t;
            }
            w->last_sent = t;
        }
        due += w->period_s;
        double now = mono_s();
        if (due < now) due = now + w->period_s; /* this process was not running: no burst of late writes */
        struct timespec ts;
        abs_time(due, &ts);
        while (!w->stop && !w->kick && mono_s() < due) {
            if (pthread_cond_timedwait(&w->cv, &w->mu, &ts) == ETIMEDOUT) break;
        }
        if (w->kick) { /* renewed after a period without a write: the beat goes out now */
            w->kick = 0;
            due = mono_s() - w->period_s;
        }
    }
    pthread_mutex_unlock(&w->mu);
    return NULL;
}

static PyObject *PeriodicWriter_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    PeriodicWriter *w = (PeriodicWriter *)type->tp_alloc(type, 0);
    if (!w) return NULL;
    pthread_mutex_init(&w->mu, NULL);
    pthread_condattr_t ca;
    pthread_condattr_init(&ca);
    pthread_condattr_setclock(&ca, CLOCK_MONOTONIC);
    pthread_cond_init(&w->cv, &ca);
    pthread_condattr_destroy(&ca);
    w->fd = -1;
    w->last_sent = -1.0;
    w->gap_s = -1.0;
    w->lease_until = INFINITY;
    return (PyObject *)w;
}

static int PeriodicWriter_init(PeriodicWriter *w, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"fd", "record", "period_s", NULL};
    int fd;
    Py_buffer rec;
    double period_s;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "iy*d", kwlist, &fd, &rec, &period_s)) return -1;
    int bad = rec.len <= 0 || (size_t)rec.len > sizeof w->rec || !(period_s > 0.0) || fd < 0 || w->started;
    if (!bad) {
        memcpy(w->rec, rec.buf, (size_t)rec.len);
        w->rec_len = (size_t)rec.len;
    }
    PyBuffer_Release(&rec);
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "PeriodicWriter(fd >= 0, record of 1..88 bytes, period_s > 0), once");
        return -1;
    }
    w->fd = fd;
    w->period_s = period_s;
    int e = pthread_create(&w->thread, NULL, writer_main, w);
    if (e) {
        errno = e;
        PyErr_SetFromErrno(PyExc_OSError);
        return -1;
    }
    w->started = 1;
    return 0;
}

static void writer_join(PeriodicWriter *w) {
    if (!w->started || w->joined) return;
    pthread_mutex_lock(&w->mu);
    w->stop = 1;
    pthread_cond_signal(&w->cv);
    pthread_mutex_unlock(&w->mu);
    pthread_join(w->thread, NULL);
    w->joined = 1;
}

static PyObject *PeriodicWriter_stop(PeriodicWriter *w, PyObject *noargs) {
    Py_BEGIN_ALLOW_THREADS
    writer_join(w);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyObject *PeriodicWriter_lease(PeriodicWriter *w, PyObject *arg) {
    double s = PyFloat_AsDouble(arg);
    if (s == -1.0 && PyErr_Occurred()) return NULL;
    double until = isinf(s) && s > 0 ? INFINITY : mono_s() + s;
    pthread_mutex_lock(&w->mu);
    w->lease_until = until;
    if (w->starved) {
        w->kick = 1;
        pthread_cond_signal(&w->cv); /* the write that waited for a lease goes out now */
    }
    pthread_mutex_unlock(&w->mu);
    Py_RETURN_NONE;
}

static PyObject *PeriodicWriter_state(PeriodicWriter *w, PyObject *args) {
    int take = 0;
    if (!PyArg_ParseTuple(args, "|p", &take)) return NULL;
    pthread_mutex_lock(&w->mu);
    long long sent = w->sent;
    double last = w->last_sent, gap = w->gap_s, gap_end = w->gap_end, err_t = w->err_t;
    int err = w->err, alive = w->started && !w->joined && !w->err;
    if (take) w->gap_s = -1.0;
    pthread_mutex_unlock(&w->mu);
    PyObject *last_o = last >= 0 ? PyFloat_FromDouble(last) : (Py_INCREF(Py_None), Py_None);
    PyObject *gap_o = gap >= 0 ? Py_BuildValue("(dd)", gap, gap_end) : (Py_INCREF(Py_None), Py_None);
    PyObject *err_o = err ? Py_BuildValue("(id)", err, err_t) : (Py_INCREF(Py_None), Py_None);
    if (!last_o || !gap_o || !err_o) {
        Py_XDECREF(last_o);
        Py_XDECREF(gap_o);
        Py_XDECREF(err_o);
        return NULL;
    }
    return Py_BuildValue("(LNNNO)", sent, last_o, gap_o, err_o, alive ? Py_True : Py_False);
}

static void PeriodicWriter_dealloc(PeriodicWriter *w) {
    Py_BEGIN_ALLOW_THREADS
    writer_join(w);
    Py_END_ALLOW_THREADS
    pthread_cond_destroy(&w->cv);
    pthread_mutex_destroy(&w->mu);
    Py_TYPE(w)->tp_free((PyObject *)w);
}

static PyMethodDef PeriodicWriter_methods[] = {
    {"lease", (PyCFunction)PeriodicWriter_lease, METH_O,
     "lease(seconds): write only until seconds from now (inf: without end); the lease of a new writer is without end"},
    {"state", (PyCFunction)PeriodicWriter_state, METH_VARARGS,
     "state(take=False) -> (sent, last write t_mono or None, (longest gap s, t_mono of the write that ended it) or None, "
     "(errno, t_mono) of the failure that ended the thread or None, running); take: forget the gap"},
    {"stop", (PyCFunction)PeriodicWriter_stop, METH_NOARGS, "stop the thread and wait for it (idempotent)"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject PeriodicWriterType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "bus.transports.hub._hubcore.PeriodicWriter",
    .tp_basicsize = sizeof(PeriodicWriter),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "PeriodicWriter(fd, record, period_s): a thread of C writes record on fd every period_s (see the file's comment).",
    .tp_new = PeriodicWriter_new,
    .tp_init = (initproc)PeriodicWriter_init,
    .tp_dealloc = (destructor)PeriodicWriter_dealloc,
    .tp_methods = PeriodicWriter_methods,
};

static PyMethodDef module_methods[] = {
    {"answer_frames", answer_frames, METH_VARARGS,
     "answer_frames(fd, other_fd, deadline_s, rx_id, rx_count, rx_len, on_frame, rest, lock) -> (n, why, errno): "
     "read fd's records; each classic data frame rx_id + i (i < rx_count) of rx_len bytes goes to on_frame(i, data), "
     "whose answers ((id, data) pairs, classic) are written at once in one send holding lock (the client's send "
     "lock); until deadline_s (CLOCK_MONOTONIC: time.monotonic()), other_fd (-1: none) readable, another record "
     "(why BURST_PYTHON) or on_frame returning None; rest (a bytearray) gets the bytes read and not handled"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef hubcore_module = {
    PyModuleDef_HEAD_INIT, "_hubcore", "The hub's data plane in C (see bus/transports/hub/_hubcore.c).", -1, module_methods,
};

PyMODINIT_FUNC PyInit__hubcore(void) {
    if (PyType_Ready(&CoreType) < 0 || PyType_Ready(&PeriodicWriterType) < 0) return NULL;
    PyObject *mod = PyModule_Create(&hubcore_module);
    if (!mod) return NULL;
    Py_INCREF(&CoreType);
    if (PyModule_AddObject(mod, "Core", (PyObject *)&CoreType) < 0) {
        Py_DECREF(&CoreType);
        Py_DECREF(mod);
        return NULL;
    }
    Py_INCREF(&PeriodicWriterType);
    if (PyModule_AddObject(mod, "PeriodicWriter", (PyObject *)&PeriodicWriterType) < 0) {
        Py_DECREF(&PeriodicWriterType);
        Py_DECREF(mod);
        return NULL;
    }
    if (PyModule_AddIntConstant(mod, "REPORT_EVENTS", REPORT_EVENTS) < 0 ||
        PyModule_AddIntConstant(mod, "REPORT_DROP", REPORT_DROP) < 0 ||
        PyModule_AddIntConstant(mod, "REPORT_REFUSE", REPORT_REFUSE) < 0 ||
        PyModule_AddIntConstant(mod, "BURST_TIMEOUT", BURST_TIMEOUT) < 0 ||
        PyModule_AddIntConstant(mod, "BURST_OTHER", BURST_OTHER) < 0 ||
        PyModule_AddIntConstant(mod, "BURST_PYTHON", BURST_PYTHON) < 0 ||
        PyModule_AddIntConstant(mod, "BURST_STOPPED", BURST_STOPPED) < 0 ||
        PyModule_AddIntConstant(mod, "BURST_CLOSED", BURST_CLOSED) < 0 ||
        PyModule_AddIntConstant(mod, "BURST_SENDFAIL", BURST_SENDFAIL) < 0) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
