/* The argument buffers of the compiled cores' entry points (afvsgp_gym.cbf._cones,
 * afvsgp_gym.gp._bank): each array is taken C-contiguous, of one dtype and length, or refused
 * with a ValueError naming it; on a refusal every buffer taken so far is released. */
#ifndef AFVSGP_CBUF_H
#define AFVSGP_CBUF_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

typedef struct {
    const char *name;
    char kind;    /* 'd' float64, 'q' int64, '?' bool */
    int writable;
} Spec;

/* The buffer of obj as spec says, with exactly n elements (any number if n < 0); -1 and a
 * ValueError naming it. */
static inline int take(PyObject *obj, Py_buffer *buf, const Spec *spec, Py_ssize_t n)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (spec->writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, buf, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous%s array", spec->name,
                     spec->writable ? ", writable" : "");
        return -1;
    }
    const char *f = buf->format;
    if (f[0] == '<' || f[0] == '=' || f[0] == '@')
        f++;
    const int ok_type = (spec->kind == 'd' && f[0] == 'd' && buf->itemsize == 8) ||
                        (spec->kind == 'q' && (f[0] == 'q' || f[0] == 'l') && buf->itemsize == 8) ||
                        (spec->kind == '?' && f[0] == '?' && buf->itemsize == 1);
    if (!ok_type || f[1] != '\0') {
        PyErr_Format(PyExc_ValueError, "%s must be of dtype %s", spec->name,
                     spec->kind == 'd' ? "float64" : spec->kind == 'q' ? "int64" : "bool");
        PyBuffer_Release(buf);
        return -1;
    }
    if (n >= 0 && buf->len / buf->itemsize != n) {
        PyErr_Format(PyExc_ValueError, "%s must hold %zd elements. Got: %zd", spec->name, n,
                     buf->len / buf->itemsize);
        PyBuffer_Release(buf);
        return -1;
    }
    return 0;
}

static inline void release_all(Py_buffer *buf, int n)
{
    for (int i = 0; i < n; i++)
        PyBuffer_Release(&buf[i]);
}

/* take() for n arrays (size[i] elements each); on failure the ones taken are released */
static inline int take_all(PyObject **obj, Py_buffer *buf, const Spec *spec,
                           const Py_ssize_t *size, int n)
{
    for (int i = 0; i < n; i++) {
        if (take(obj[i], &buf[i], &spec[i], size[i]) < 0) {
            release_all(buf, i);
            return -1;
        }
    }
    return 0;
}

#endif
