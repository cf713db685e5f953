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
    return m;
}
