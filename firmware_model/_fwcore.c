/*
 * _fwcore.c -- the CPython extension firmware_model._fwcore: the drive firmware's C core
 * (firmware_model/c/ilc_control.c, interface firmware_model/c/ilc_drive.h) for software in the
 * loop.  Built by setup.py (optional: without a C compiler the install still succeeds and only
 * the Python firmware is there).
 *
 * control_tick(count, idx, rec_idx, st, tables, rec) -> (tau, status) has the signature and the
 * semantics of the numba kernel firmware_model.control_law.control_tick: st int64 (26,), tables
 * int32 (3, cols), rec int32 (4, rec_cols), all C-contiguous (st and rec writable), reached
 * through the buffer protocol.  A wrong dtype/dimension/contiguity is a TypeError, a wrong shape
 * a ValueError, an index outside its array an IndexError (the numba kernel does not check; the
 * C core must not write out of bounds).
 *
 * TrialTicker runs a drive's plain io ticks of a trial for the hub client's answer loop, outside the
 * interpreter (firmware_model/plain_ticks.py; its comment below says what it does and when it hands a
 * tick to the Python path).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "c/ilc_drive.h"

/* A buffer's item is a signed integer of `size` bytes (struct-module format, native or standard
 * byte order of this machine). */
static int format_is_int(const char *format, Py_ssize_t itemsize, Py_ssize_t size)
{
    char code;
    if (format == NULL || itemsize != size) {
        return 0;
    }
    if (format[0] == '@' || format[0] == '=' || format[0] == '<' || format[0] == '!' || format[0] == '>') {
#if PY_LITTLE_ENDIAN
        if (format[0] == '>' || format[0] == '!') {
            return 0;
        }
#else
        if (format[0] == '<') {
            return 0;
        }
#endif
        ++format;
    }
    code = format[0];
    if (format[1] != '\0') {
        return 0;
    }
    return code == 'b' || code == 'h' || code == 'i' || code == 'l' || code == 'q';
}

/* Get a C-contiguous buffer of `ndim` dimensions of signed `itemsize`-byte integers. */
static int get_array(PyObject *obj, Py_buffer *view, int writable, int ndim, Py_ssize_t itemsize,
                     const char *name)
{
    int flags = PyBUF_FORMAT | PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) != 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s must be a C-contiguous%s int%d array", name,
                     writable ? ", writable" : "", (int)(itemsize * 8));
        return -1;
    }
    if (!format_is_int(view->format, view->itemsize, itemsize) || view->ndim != ndim) {
        PyErr_Format(PyExc_TypeError, "%s must be a %d-D int%d array", name, ndim, (int)(itemsize * 8));
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

static PyObject *fw_control_tick(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer st, tables, rec;
    long long count, idx, rec_idx;
    int32_t status = ILC_STATUS_OK;
    int32_t tau;
    PyObject *result = NULL;

    (void)self;
    if (nargs != 6) {
        PyErr_Format(PyExc_TypeError, "control_tick() takes 6 arguments (%zd given)", nargs);
        return NULL;
    }
    count = PyLong_AsLongLong(args[0]);
    if (count == -1 && PyErr_Occurred()) {
        return NULL;
    }
    idx = PyLong_AsLongLong(args[1]);
    if (idx == -1 && PyErr_Occurred()) {
        return NULL;
    }
    rec_idx = PyLong_AsLongLong(args[2]);
    if (rec_idx == -1 && PyErr_Occurred()) {
        return NULL;
    }
    if (get_array(args[3], &st, 1, 1, 8, "st") != 0) {
        return NULL;
    }
    if (get_array(args[4], &tables, 0, 2, 4, "tables") != 0) {
        goto release_st;
    }
    if (get_array(args[5], &rec, 1, 2, 4, "rec") != 0) {
        goto release_tables;
    }
    if (st.shape[0] != ILC_N_STATE) {
        PyErr_Format(PyExc_ValueError, "st must have shape (%d,), got (%zd,)", ILC_N_STATE, st.shape[0]);
        goto release_all;
    }
    if (tables.shape[0] != 3) {
        PyErr_Format(PyExc_ValueError, "tables must have 3 rows, got %zd", tables.shape[0]);
        goto release_all;
    }
    if (rec.shape[0] != 4) {
        PyErr_Format(PyExc_ValueError, "rec must have 4 rows, got %zd", rec.shape[0]);
        goto release_all;
    }
    if (idx < 0 || idx >= (long long)tables.shape[1]) {
        PyErr_Format(PyExc_IndexError, "idx %lld outside the %zd table columns", idx, tables.shape[1]);
        goto release_all;
    }
    if (rec_idx < -1 || rec_idx >= (long long)rec.shape[1]) {
        PyErr_Format(PyExc_IndexError, "rec_idx %lld outside -1 .. %zd", rec_idx, rec.shape[1] - 1);
        goto release_all;
    }
    tau = ilc_control_tick((int64_t)count, (int64_t)idx, (int64_t)rec_idx, (int64_t *)st.buf,
                           (const int32_t *)tables.buf, (int64_t)tables.shape[1], (int32_t *)rec.buf,
                           (int64_t)rec.shape[1], &status);
    result = Py_BuildValue("(ii)", (int)tau, (int)status);
release_all:
    PyBuffer_Release(&rec);
release_tables:
    PyBuffer_Release(&tables);
release_st:
    PyBuffer_Release(&st);
    return result;
}

static PyObject *fw_rshift_round(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long x;
    long q;
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "rshift_round() takes 2 arguments");
        return NULL;
    }
    x = PyLong_AsLongLong(args[0]);
    if (x == -1 && PyErr_Occurred()) {
        return NULL;
    }
    q = PyLong_AsLong(args[1]);
    if (q == -1 && PyErr_Occurred()) {
        return NULL;
    }
    if (q > 62) {
        PyErr_SetString(PyExc_ValueError, "rshift_round(): q must be <= 62");
        return NULL;
    }
    return PyLong_FromLongLong((long long)ilc_rshift_round((int64_t)x, (int)q));
}

/* The int64 arguments of a helper (OverflowError outside int64). */
static int int64_args(const char *name, PyObject *const *args, Py_ssize_t nargs, Py_ssize_t n, int64_t *out)
{
    Py_ssize_t i;
    if (nargs != n) {
        PyErr_Format(PyExc_TypeError, "%s() takes %zd arguments (%zd given)", name, n, nargs);
        return -1;
    }
    for (i = 0; i < n; ++i) {
        long long v = PyLong_AsLongLong(args[i]);
        if (v == -1 && PyErr_Occurred()) {
            return -1;
        }
        out[i] = (int64_t)v;
    }
    return 0;
}

static PyObject *fw_csp_velocity_ref(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t a[3];
    (void)self;
    if (int64_args("csp_velocity_ref", args, nargs, 3, a) != 0) {
        return NULL;
    }
    return PyLong_FromLong((long)ilc_csp_velocity_ref(a[0], a[1], a[2]));
}

static PyObject *fw_velocity_from_tick_q16(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t a[2];
    (void)self;
    if (int64_args("velocity_from_tick_q16", args, nargs, 2, a) != 0) {
        return NULL;
    }
    if (a[1] < 1 || a[1] > 100000 || a[0] >= (INT64_C(1) << 62) || a[0] <= -(INT64_C(1) << 62)) {
        PyErr_SetString(PyExc_ValueError, "velocity_from_tick_q16(): period_us 1..100000, |v_q16| < 2^62");
        return NULL;
    }
    return PyLong_FromLong((long)ilc_velocity_from_tick_q16(a[0], a[1]));
}

static PyObject *fw_torque_units_to_permille(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t a[2];
    (void)self;
    if (int64_args("torque_units_to_permille", args, nargs, 2, a) != 0) {
        return NULL;
    }
    if (a[0] >= (INT64_C(1) << 61) || a[0] <= -(INT64_C(1) << 61) || a[1] >= (INT64_C(1) << 32)) {
        PyErr_SetString(PyExc_ValueError, "torque_units_to_permille(): |tau_units| < 2^61, rated_mnm < 2^32");
        return NULL;
    }
    return PyLong_FromLong((long)ilc_torque_units_to_permille(a[0], a[1]));
}

/* ---------------------------------------------------------------- the trial's plain ticks
 * TrialTicker: a drive's plain io ticks of a trial in table playback, outside the interpreter
 * (firmware_model/plain_ticks.py arms it; the hub client's answer loop calls it once per encoder
 * frame, bus/transports/hub/_hubcore.c answer_frames).  Armed, ticker(index, data) with the
 * encoder frame's 6 data bytes does what the Python path of the drive node does for a plain tick
 * (DriveNode._answer_tick: the wire tick widened, Drive.io_tick, TablePlaybackMode.tick, the
 * kernel, the torque frame and its status) and writes back what that path changes:
 * drive.time_us, trial.next_tick, node._next_full_tick, node.frames_out.  Anything else goes to
 * the Python path unchanged, fallback(index, data), after the ticker disarmed itself: a tick out
 * of sequence, the trial's last tick, the service's deadline reached (clock() >= serve_by_s), a
 * kernel status (the state and the recorder column the kernel wrote are put back first, so that
 * the Python path runs the same tick from the same state).  Disarmed, every call is fallback's.
 * The kernel is this module's ilc_control_tick when the drive runs it (--firmware c), else the
 * drive's kernel object, called with the Python path's arguments (the Python model's numba
 * kernel). */

static PyObject *str_time_us, *str_next_tick, *str_next_full_tick, *str_frames_out;
static PyObject *fw_control_tick_obj; /* this module's control_tick: a drive that runs the C core */

typedef struct {
    PyObject_HEAD
    PyObject *fallback, *clock, *kernel, *node, *drive, *trial;
    PyObject *st_obj, *tables_obj, *rec_obj; /* while armed */
    Py_buffer st, tables, rec;               /* while armed */
    int armed, direct;
    long long next_tick, n_table, next_full_tick, tick_origin, time_us, period_us, offset, frames_out;
    double serve_by_s;
    int status_base, status_limited;
    unsigned int torque_id;
    long long ticks; /* ticks run here since the ticker was made */
} TickerObject;

static void ticker_release(TickerObject *self)
{
    if (self->armed) {
        PyBuffer_Release(&self->st);
        PyBuffer_Release(&self->tables);
        PyBuffer_Release(&self->rec);
        self->armed = 0;
    }
    Py_CLEAR(self->st_obj);
    Py_CLEAR(self->tables_obj);
    Py_CLEAR(self->rec_obj);
}

static int ticker_init(TickerObject *self, PyObject *args, PyObject *kwds)
{
    PyObject *fallback, *clock, *kernel, *node, *drive, *trial;
    unsigned int torque_id;
    static char *kwlist[] = {"fallback", "clock", "kernel", "node", "drive", "trial", "torque_id", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "OOOOOOI:TrialTicker", kwlist, &fallback, &clock, &kernel,
                                     &node, &drive, &trial, &torque_id)) {
        return -1;
    }
    if (!PyCallable_Check(fallback) || !PyCallable_Check(clock) || !PyCallable_Check(kernel)) {
        PyErr_SetString(PyExc_TypeError, "TrialTicker: fallback, clock and kernel must be callable");
        return -1;
    }
    if (torque_id > 0x7FF) {
        PyErr_Format(PyExc_ValueError, "TrialTicker: torque_id 0x%X is not an 11-bit identifier", torque_id);
        return -1;
    }
    ticker_release(self);
    Py_INCREF(fallback);
    Py_XSETREF(self->fallback, fallback);
    Py_INCREF(clock);
    Py_XSETREF(self->clock, clock);
    Py_INCREF(kernel);
    Py_XSETREF(self->kernel, kernel);
    Py_INCREF(node);
    Py_XSETREF(self->node, node);
    Py_INCREF(drive);
    Py_XSETREF(self->drive, drive);
    Py_INCREF(trial);
    Py_XSETREF(self->trial, trial);
    self->direct = kernel == fw_control_tick_obj;
    self->torque_id = torque_id;
    return 0;
}

static int ticker_traverse(TickerObject *self, visitproc visit, void *arg)
{
    Py_VISIT(self->fallback);
    Py_VISIT(self->clock);
    Py_VISIT(self->kernel);
    Py_VISIT(self->node);
    Py_VISIT(self->drive);
    Py_VISIT(self->trial);
    Py_VISIT(self->st_obj);
    Py_VISIT(self->tables_obj);
    Py_VISIT(self->rec_obj);
    return 0;
}

static int ticker_clear(TickerObject *self)
{
    ticker_release(self);
    Py_CLEAR(self->fallback);
    Py_CLEAR(self->clock);
    Py_CLEAR(self->kernel);
    Py_CLEAR(self->node);
    Py_CLEAR(self->drive);
    Py_CLEAR(self->trial);
    return 0;
}

static void ticker_dealloc(TickerObject *self)
{
    PyObject_GC_UnTrack(self);
    ticker_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* arm(st, tables, rec, next_tick, n_table, next_full_tick, tick_origin, time_us, period_us, offset,
 *     frames_out, serve_by_s, status_base, status_limited) */
static PyObject *ticker_arm(TickerObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long v[8];
    long status[2];
    double serve_by;
    if (nargs != 14) {
        PyErr_Format(PyExc_TypeError, "arm() takes 14 arguments (%zd given)", nargs);
        return NULL;
    }
    for (int i = 0; i < 8; i++) {
        v[i] = PyLong_AsLongLong(args[3 + i]);
        if (v[i] == -1 && PyErr_Occurred()) return NULL;
    }
    serve_by = PyFloat_AsDouble(args[11]);
    if (serve_by == -1.0 && PyErr_Occurred()) return NULL;
    for (int i = 0; i < 2; i++) {
        status[i] = PyLong_AsLong(args[12 + i]);
        if (status[i] == -1 && PyErr_Occurred()) return NULL;
        if (status[i] < 0 || status[i] > 0xFF) {
            PyErr_SetString(PyExc_ValueError, "arm(): a torque status outside 0..255");
            return NULL;
        }
    }
    /* the tick numbers stay far from overflow; time_us counts up by period_us per tick */
    if (v[0] < 0 || v[1] < 0 || v[2] < 0 || v[0] > INT32_MAX || v[1] > INT32_MAX || v[2] > INT32_MAX ||
        v[3] < 0 || v[3] > 0xFFFF || v[4] < 0 || v[4] > (INT64_C(1) << 62) || v[5] < 0 || v[5] > INT32_MAX ||
        v[6] < INT32_MIN || v[6] > INT32_MAX || v[7] < 0) {
        PyErr_SetString(PyExc_ValueError, "arm(): a tick, time, period, offset or count outside its range");
        return NULL;
    }
    ticker_release(self);
    if (get_array(args[0], &self->st, 1, 1, 8, "st") != 0) return NULL;
    if (get_array(args[1], &self->tables, 0, 2, 4, "tables") != 0) {
        PyBuffer_Release(&self->st);
        return NULL;
    }
    if (get_array(args[2], &self->rec, 1, 2, 4, "rec") != 0) {
        PyBuffer_Release(&self->st);
        PyBuffer_Release(&self->tables);
        return NULL;
    }
    self->armed = 1; /* the three buffers are held: ticker_release gives them back */
    if (self->st.shape[0] != ILC_N_STATE || self->tables.shape[0] != 3 || self->rec.shape[0] != 4) {
        ticker_release(self);
        PyErr_Format(PyExc_ValueError, "arm(): st (%d,), tables (3, n) and rec (4, n) expected", ILC_N_STATE);
        return NULL;
    }
    Py_INCREF(args[0]);
    self->st_obj = args[0];
    Py_INCREF(args[1]);
    self->tables_obj = args[1];
    Py_INCREF(args[2]);
    self->rec_obj = args[2];
    self->next_tick = v[0];
    self->n_table = v[1];
    self->next_full_tick = v[2];
    self->tick_origin = v[3];
    self->time_us = v[4];
    self->period_us = v[5];
    self->offset = v[6];
    self->frames_out = v[7];
    self->serve_by_s = serve_by;
    self->status_base = (int)status[0];
    self->status_limited = (int)status[1];
    Py_RETURN_NONE;
}

static PyObject *ticker_disarm(TickerObject *self, PyObject *Py_UNUSED(ignored))
{
    ticker_release(self);
    Py_RETURN_NONE;
}

/* the Python path for this frame, the ticker disarmed */
static PyObject *ticker_fall_back(TickerObject *self, PyObject *args, PyObject *kwds)
{
    ticker_release(self);
    return PyObject_Call(self->fallback, args, kwds);
}

/* obj.name = value (a new int) */
static int set_int(PyObject *obj, PyObject *name, long long value)
{
    PyObject *v = PyLong_FromLongLong(value);
    if (!v) return -1;
    int rc = PyObject_SetAttr(obj, name, v);
    Py_DECREF(v);
    return rc;
}

static PyObject *ticker_call(TickerObject *self, PyObject *args, PyObject *kwds)
{
    PyObject *data;
    if (!self->armed || kwds || PyTuple_GET_SIZE(args) != 2) return ticker_fall_back(self, args, kwds);
    data = PyTuple_GET_ITEM(args, 1);
    if (!PyBytes_Check(data) || PyBytes_GET_SIZE(data) != 6) return ticker_fall_back(self, args, kwds);
    const uint8_t *b = (const uint8_t *)PyBytes_AS_STRING(data);
    int32_t count = (int32_t)((uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24);
    unsigned int wire = (unsigned int)b[4] | (unsigned int)b[5] << 8;
    /* io_frames.tick_diff: the wire tick relative to the trial's origin, widened */
    long long rel = ((long long)wire - self->tick_origin) & 0xFFFF;
    long long tick = self->next_full_tick + (((rel - self->next_full_tick + 0x8000) & 0xFFFF) - 0x8000);
    int64_t tab_cols = (int64_t)self->tables.shape[1], rec_cols = (int64_t)self->rec.shape[1];
    if (tick != self->next_tick || tick < 0 || tick + 1 >= self->n_table || tick >= tab_cols || tick >= rec_cols) {
        return ticker_fall_back(self, args, kwds); /* out of sequence, or the trial's last tick */
    }
    PyObject *now_obj = PyObject_CallNoArgs(self->clock);
    if (!now_obj) return NULL;
    double now = PyFloat_AsDouble(now_obj);
    Py_DECREF(now_obj);
    if (now == -1.0 && PyErr_Occurred()) return NULL;
    if (!(now < self->serve_by_s)) return ticker_fall_back(self, args, kwds); /* the service is due */
    int64_t *st = (int64_t *)self->st.buf;
    int32_t *rec = (int32_t *)self->rec.buf;
    int64_t st_before[ILC_N_STATE];
    int32_t rec_before[4];
    memcpy(st_before, st, sizeof st_before);
    for (int r = 0; r < 4; r++) rec_before[r] = rec[r * rec_cols + tick];
    long long pos = self->offset ? ilc_sat32((int64_t)count + self->offset) : (long long)count;
    int32_t status = ILC_STATUS_OK;
    long long tau;
    if (self->direct) {
        tau = ilc_control_tick(pos, tick, tick, st, (const int32_t *)self->tables.buf, tab_cols, rec, rec_cols, &status);
    } else {
        PyObject *res = PyObject_CallFunction(self->kernel, "LLLOOO", pos, tick, tick, self->st_obj, self->tables_obj,
                                              self->rec_obj);
        if (!res) {
            ticker_release(self);
            return NULL;
        }
        long long pair[2] = {0, 0};
        if (!PyTuple_Check(res) || PyTuple_GET_SIZE(res) != 2) {
            Py_DECREF(res);
            ticker_release(self);
            PyErr_SetString(PyExc_TypeError, "TrialTicker: the kernel must return (torque, status)");
            return NULL;
        }
        for (int i = 0; i < 2; i++) {
            pair[i] = PyLong_AsLongLong(PyTuple_GET_ITEM(res, i));
            if (pair[i] == -1 && PyErr_Occurred()) {
                Py_DECREF(res);
                ticker_release(self);
                return NULL;
            }
        }
        Py_DECREF(res);
        if (pair[0] < INT32_MIN || pair[0] > INT32_MAX) {
            ticker_release(self);
            PyErr_Format(PyExc_ValueError, "TrialTicker: torque %lld outside int32", pair[0]);
            return NULL;
        }
        tau = pair[0];
        status = pair[1] != ILC_STATUS_OK;
    }
    if (status != ILC_STATUS_OK) { /* a following error: the Python path, from the state before */
        memcpy(st, st_before, sizeof st_before);
        for (int r = 0; r < 4; r++) rec[r * rec_cols + tick] = rec_before[r];
        return ticker_fall_back(self, args, kwds);
    }
    self->time_us += self->period_us;
    self->next_tick = self->next_full_tick = tick + 1;
    self->frames_out++;
    self->ticks++;
    if (set_int(self->drive, str_time_us, self->time_us) || set_int(self->trial, str_next_tick, self->next_tick) ||
        set_int(self->node, str_next_full_tick, self->next_full_tick) ||
        set_int(self->node, str_frames_out, self->frames_out)) {
        ticker_release(self);
        return NULL;
    }
    uint8_t out[7];
    uint32_t t = (uint32_t)(int32_t)tau;
    out[0] = (uint8_t)t;
    out[1] = (uint8_t)(t >> 8);
    out[2] = (uint8_t)(t >> 16);
    out[3] = (uint8_t)(t >> 24);
    out[4] = (uint8_t)wire;
    out[5] = (uint8_t)(wire >> 8);
    out[6] = (uint8_t)(st[ILC_S_LIMITED] ? self->status_limited : self->status_base);
    return Py_BuildValue("((Iy#))", self->torque_id, (const char *)out, (Py_ssize_t)sizeof out);
}

static PyObject *ticker_get_armed(TickerObject *self, void *Py_UNUSED(closure))
{
    return PyBool_FromLong(self->armed);
}

static PyObject *ticker_get_ticks(TickerObject *self, void *Py_UNUSED(closure))
{
    return PyLong_FromLongLong(self->ticks);
}

static PyMethodDef ticker_methods[] = {
    {"arm", (PyCFunction)(void (*)(void))ticker_arm, METH_FASTCALL,
     "arm(st, tables, rec, next_tick, n_table, next_full_tick, tick_origin, time_us, period_us, offset, "
     "frames_out, serve_by_s, status_base, status_limited): the state of a plain trial, valid until the Python "
     "path runs again (firmware_model/plain_ticks.py)"},
    {"disarm", (PyCFunction)ticker_disarm, METH_NOARGS, "disarm(): every frame to the Python path"},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef ticker_getset[] = {
    {"armed", (getter)ticker_get_armed, NULL, "True while the ticker runs plain ticks", NULL},
    {"ticks", (getter)ticker_get_ticks, NULL, "ticks the ticker ran since it was made", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject TickerType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "firmware_model._fwcore.TrialTicker",
    .tp_basicsize = sizeof(TickerObject),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "TrialTicker(fallback, clock, kernel, node, drive, trial, torque_id): a drive's plain io ticks of a "
              "trial in table playback, outside the interpreter (firmware_model/_fwcore.c)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)ticker_init,
    .tp_dealloc = (destructor)ticker_dealloc,
    .tp_traverse = (traverseproc)ticker_traverse,
    .tp_clear = (inquiry)ticker_clear,
    .tp_call = (ternaryfunc)ticker_call,
    .tp_methods = ticker_methods,
    .tp_getset = ticker_getset,
};

static PyMethodDef fw_methods[] = {
    {"control_tick", (PyCFunction)(void (*)(void))fw_control_tick, METH_FASTCALL,
     "control_tick(count, idx, rec_idx, st, tables, rec) -> (tau, status): one control period "
     "of the C core (firmware_model/c/ilc_control.c), as firmware_model.control_law.control_tick."},
    {"rshift_round", (PyCFunction)(void (*)(void))fw_rshift_round, METH_FASTCALL,
     "rshift_round(x, q) -> int: the C core's rounding right shift (bus.fixedpoint.rshift_round)."},
    {"csp_velocity_ref", (PyCFunction)(void (*)(void))fw_csp_velocity_ref, METH_FASTCALL,
     "csp_velocity_ref(target, prev, rate_q12) -> int: ilc_csp_velocity_ref (CspMode's velocity reference)."},
    {"velocity_from_tick_q16", (PyCFunction)(void (*)(void))fw_velocity_from_tick_q16, METH_FASTCALL,
     "velocity_from_tick_q16(v_q16, period_us) -> int: bus.fixedpoint.velocity_from_tick_q16 in C."},
    {"torque_units_to_permille", (PyCFunction)(void (*)(void))fw_torque_units_to_permille, METH_FASTCALL,
     "torque_units_to_permille(tau_units, rated_mnm) -> int: bus.fixedpoint.torque_units_to_permille in C."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef fw_module = {
    PyModuleDef_HEAD_INIT, "_fwcore",
    "The drive firmware's C core (firmware_model/c/) as a CPython extension: software in the loop.",
    -1, fw_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__fwcore(void)
{
    PyObject *m = PyModule_Create(&fw_module);
    if (m == NULL) {
        return NULL;
    }
    /* every constant of ilc_drive.h, without the ILC_ prefix */
    if (PyModule_AddIntConstant(m, "N_STATE", ILC_N_STATE) != 0 ||
        PyModule_AddIntConstant(m, "P_KP", ILC_P_KP) != 0 ||
        PyModule_AddIntConstant(m, "P_KD", ILC_P_KD) != 0 ||
        PyModule_AddIntConstant(m, "P_ALPHA", ILC_P_ALPHA) != 0 ||
        PyModule_AddIntConstant(m, "P_RATE", ILC_P_RATE) != 0 ||
        PyModule_AddIntConstant(m, "P_TLIM", ILC_P_TLIM) != 0 ||
        PyModule_AddIntConstant(m, "P_FE_WINDOW", ILC_P_FE_WINDOW) != 0 ||
        PyModule_AddIntConstant(m, "S_PREV_COUNT", ILC_S_PREV_COUNT) != 0 ||
        PyModule_AddIntConstant(m, "S_HAVE_PREV", ILC_S_HAVE_PREV) != 0 ||
        PyModule_AddIntConstant(m, "S_VF", ILC_S_VF) != 0 ||
        PyModule_AddIntConstant(m, "S_VEST", ILC_S_VEST) != 0 ||
        PyModule_AddIntConstant(m, "S_POS", ILC_S_POS) != 0 ||
        PyModule_AddIntConstant(m, "S_TAU", ILC_S_TAU) != 0 ||
        PyModule_AddIntConstant(m, "S_TAU_FB", ILC_S_TAU_FB) != 0 ||
        PyModule_AddIntConstant(m, "S_ERR", ILC_S_ERR) != 0 ||
        PyModule_AddIntConstant(m, "S_LIMITED", ILC_S_LIMITED) != 0 ||
        PyModule_AddIntConstant(m, "P_LOOP", ILC_P_LOOP) != 0 ||
        PyModule_AddIntConstant(m, "P_KPP", ILC_P_KPP) != 0 ||
        PyModule_AddIntConstant(m, "P_KVFF", ILC_P_KVFF) != 0 ||
        PyModule_AddIntConstant(m, "P_KTFF", ILC_P_KTFF) != 0 ||
        PyModule_AddIntConstant(m, "P_KVP", ILC_P_KVP) != 0 ||
        PyModule_AddIntConstant(m, "P_KVI", ILC_P_KVI) != 0 ||
        PyModule_AddIntConstant(m, "S_VINT", ILC_S_VINT) != 0 ||
        PyModule_AddIntConstant(m, "S_VCMD", ILC_S_VCMD) != 0 ||
        PyModule_AddIntConstant(m, "P_FE_TICKS", ILC_P_FE_TICKS) != 0 ||
        PyModule_AddIntConstant(m, "S_FE_COUNT", ILC_S_FE_COUNT) != 0 ||
        PyModule_AddIntConstant(m, "LOOP_PD", ILC_LOOP_PD) != 0 ||
        PyModule_AddIntConstant(m, "LOOP_CASCADE", ILC_LOOP_CASCADE) != 0 ||
        PyModule_AddIntConstant(m, "ROW_REF_POS", ILC_ROW_REF_POS) != 0 ||
        PyModule_AddIntConstant(m, "ROW_REF_VEL", ILC_ROW_REF_VEL) != 0 ||
        PyModule_AddIntConstant(m, "ROW_FF", ILC_ROW_FF) != 0 ||
        PyModule_AddIntConstant(m, "REC_POS", ILC_REC_POS) != 0 ||
        PyModule_AddIntConstant(m, "REC_VEL", ILC_REC_VEL) != 0 ||
        PyModule_AddIntConstant(m, "REC_TAU", ILC_REC_TAU) != 0 ||
        PyModule_AddIntConstant(m, "REC_TAU_FB", ILC_REC_TAU_FB) != 0 ||
        PyModule_AddIntConstant(m, "ACC_Q", ILC_ACC_Q) != 0 ||
        PyModule_AddIntConstant(m, "GAIN_Q", ILC_GAIN_Q) != 0 ||
        PyModule_AddIntConstant(m, "VEL_FILTER_Q", ILC_VEL_FILTER_Q) != 0 ||
        PyModule_AddIntConstant(m, "VEL_STATE_Q", ILC_VEL_STATE_Q) != 0 ||
        PyModule_AddIntConstant(m, "RATE_Q", ILC_RATE_Q) != 0 ||
        PyModule_AddIntConstant(m, "STATUS_OK", ILC_STATUS_OK) != 0 ||
        PyModule_AddIntConstant(m, "STATUS_FOLLOWING_ERROR", ILC_STATUS_FOLLOWING_ERROR) != 0) {
        Py_DECREF(m);
        return NULL;
    }
    str_time_us = PyUnicode_InternFromString("time_us");
    str_next_tick = PyUnicode_InternFromString("next_tick");
    str_next_full_tick = PyUnicode_InternFromString("_next_full_tick");
    str_frames_out = PyUnicode_InternFromString("frames_out");
    fw_control_tick_obj = PyObject_GetAttrString(m, "control_tick");
    if (!str_time_us || !str_next_tick || !str_next_full_tick || !str_frames_out || !fw_control_tick_obj ||
        PyType_Ready(&TickerType) < 0 || PyModule_AddObjectRef(m, "TrialTicker", (PyObject *)&TickerType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
