/* _symkf_fastcall: one filter step from Python with the input contract checked in C.
 *
 * A Step is made once per filter and measurement (symkf/runtime/fastcall.py) from the addresses
 * of the buffers the compiled kernel is bound to: the kernel's `<model>_<kernel>_v` entry, its
 * argument-pointer array, the t and dt buffers, the filter's clock (its time after the last step)
 * and one slot per array argument of the Python call (z, q, mask, u, ...). Calling it with
 * (t, dt, array_0, ..., array_n-1):
 *
 *   1. checks every argument without writing anything: t, dt Python floats (numpy.float64 is
 *      one), finite, dt > 0, t the clock's time (None: the clock's time); each array a native float64 1-D buffer
 *      (any stride, e.g. a row of a column-major matrix) of the slot's size with finite entries
 *      (a mask: exactly 0 or 1; a measurement z: finite where its mask uses it, as the kernel
 *      reads it), or None where the slot allows it;
 *   2. copies the values into the bound buffers (a None mask writes ones, a None magnetometer
 *      sample zeros, a None input keeps the held value);
 *   3. calls the kernel; on success (status 0 or gated) sets the clock to t + dt, counts the
 *      call (`Step.calls`) and returns the status code (an int).
 *
 * A Step may also have a trusted kernel (Step.trusted; the C run loop's `trusted` partner of the
 * step, codegen/spec.py Kernel.trusted): the same x, P and codes without the checks that the
 * filter's own state cannot fail (|q| = 1, P PSD, R diagonal) and without the diagnostics y, S.
 * It is called instead once a step has succeeded and nothing was written from Python since (the
 * filter's `own` flag: set here, cleared by every write of the Python Filter). Before it runs,
 * the step's carried state is read; after it succeeded that state and the step's per-step inputs
 * are kept in the filter's replay buffers and the measurement's `stale` flag is set, so that y and
 * S, when asked for, are computed by the checked step from exactly those inputs
 * (symkf/runtime/fastpath.py). A failed step keeps nothing: the replay stays the last success's.
 *
 * Whatever it does not accept it returns None for, having written nothing: the caller then runs
 * the Python contract (symkf/runtime/contract.py), which accepts or refuses it with a clear error.
 * A kernel failure (x and P unchanged) also returns None, with the clock and count unchanged:
 * the Python path then calls again and raises the error with its details.
 * So this file adds speed, never a rule: every call it accepts, the Python path accepts too and
 * writes the very same values. Arrays are read through the buffer protocol; with SYMKF_NUMPY
 * (numpy's headers found at build time) an exact numpy.ndarray is read from its fields instead,
 * which skips the buffer export numpy builds for every new row view. Each array's values are
 * copied once into a local array, checked there and written from there.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>
#ifdef SYMKF_NUMPY
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>
#endif
#include <float.h>
#include <math.h>
#include <stddef.h>
#include <string.h>

#define MAX_SLOTS 8
#define MAX_SIZE 64   /* entries per array argument (per-call vectors are small) */
#define MAX_SAVES 16
#define MAX_SAVED 1024  /* carried entries a trusted step reads before its call (x, P) */

/* What a slot does with None: */
enum { NONE_KEEP = 0,     /* keep the buffer (an input held from the last call; or size 0) */
       NONE_ONES = 1,     /* write ones (a mask: every component used) */
       NONE_ZEROS = 2,    /* write zeros (a MARG sample: skip that correction) */
       NONE_DECLINE = 3,  /* let Python answer (a required argument) */
       ABSENT = 4 };      /* the kernel has no such argument: only None is accepted here */
/* How a slot's values are checked: */
enum { CHECK_FINITE = 0,  /* every entry finite */
       CHECK_MASK = 1,    /* every entry exactly 0 or 1 (the availability mask) */
       CHECK_USED = 2 };  /* finite where the mask slot uses the component (a NaN that is masked
                             out is never read: the kernel's z_used is 0 there) */

typedef int (*kernel_v)(double *const *args);

typedef struct {
  double *dst;
  Py_ssize_t size;
  int if_none;
  int check;
} Slot;

/* One buffer a trusted step keeps: n entries from `from` (a bound buffer) into `into` (its replay);
   `carried`: the kernel overwrites `from` (x, P), so it is read before the call. */
typedef struct {
  const double *from;
  double *into;
  Py_ssize_t n;
  int carried;
} Save;

typedef struct {
  PyObject_HEAD
  vectorcallfunc vectorcall;
  kernel_v kernel;
  double *const *args;
  double *t, *dt;
  double *clock;        /* the filter's time after a step (NULL: none; t None is then declined) */
  int gated;            /* the status code of a gated update (a success: codegen/spec.py) */
  int n_slots;
  int mask_slot;        /* index of the CHECK_MASK slot, -1 if none */
  Py_ssize_t calls;     /* calls that took this path and succeeded */
  Slot slots[MAX_SLOTS];
  kernel_v trusted;     /* NULL: none (see the top of this file) */
  double *const *trusted_args;
  double *own;          /* the filter's flag: 1 once a step succeeded, 0 after any write from Python */
  double *stale;        /* the measurement's flag: 1 while its y, S are left to the replay */
  int n_saves, n_carried;   /* the carried saves first */
  Save saves[MAX_SAVES];
  Py_ssize_t trusted_calls;
  PyObject *keep_alive;
} Step;

/* A Python float (or subclass: numpy.float64 is one, tested first by its type) that is finite. */
#ifdef SYMKF_NUMPY
#define FLOAT64_SCALAR(o) (Py_TYPE(o) == &PyDoubleArrType_Type)
#else
#define FLOAT64_SCALAR(o) 0
#endif
static int finite_float(PyObject *o, double *value) {
  if (!(PyFloat_CheckExact(o) || FLOAT64_SCALAR(o) || PyFloat_Check(o))) return 0;
  *value = PyFloat_AS_DOUBLE(o);
  return isfinite(*value);
}

static int native_double(const char *format) {
  const unsigned one = 1;
  const int little = *(const unsigned char *) &one == 1;
  if (format == NULL) return 0;
  if (format[0] == '@' || format[0] == '=' || format[0] == (little ? '<' : '>')) ++format;
  return format[0] == 'd' && format[1] == '\0';
}

/* One array argument, read: its values copied here (so that checking and writing them read a
   small contiguous array, and an input that is itself a bound buffer cannot alias the write). */
typedef struct {
  int given;                 /* 0: the argument was None */
  double values[MAX_SIZE];
} Input;

/* 1 if the n values pass `check`: finite (CHECK_FINITE), exactly 0 or 1 (CHECK_MASK); CHECK_USED
   is checked later against the mask (used_ok). */
static int checked(const double *v, Py_ssize_t n, int check) {
  Py_ssize_t i;
  double sum = 0.0;
  if (check == CHECK_MASK) {
    for (i = 0; i < n; ++i) if (v[i] != 0.0 && v[i] != 1.0) return 0;
  } else if (check == CHECK_FINITE) {
    for (i = 0; i < n; ++i) sum += v[i] - v[i];      /* 0 unless an entry is NaN or +-Inf (then NaN) */
    return sum == 0.0;
  }
  return 1;
}

static void gather(Input *in, const char *buf, Py_ssize_t stride, Py_ssize_t n) {
  Py_ssize_t i;
  if (stride == (Py_ssize_t) sizeof(double)) {
    memcpy(in->values, buf, (size_t) n * sizeof(double));
    return;
  }
  for (i = 0; i < n; ++i, buf += stride) memcpy(&in->values[i], buf, sizeof(double));
}

/* 1: `o` is a list or tuple of `size` Python floats or ints (not bools), read into in->values.
   A float converts exactly; an int as PyLong_AsDouble (correctly rounded, as numpy converts it). */
static int sequence_ok(const Slot *slot, PyObject *o, Input *in) {
  Py_ssize_t i, n = PySequence_Fast_GET_SIZE(o);
  PyObject **items = PySequence_Fast_ITEMS(o);
  if (n != slot->size || n > MAX_SIZE) return 0;
  for (i = 0; i < n; ++i) {
    PyObject *item = items[i];
    if (PyFloat_Check(item)) in->values[i] = PyFloat_AS_DOUBLE(item);
    else if (PyLong_CheckExact(item)) {
      in->values[i] = PyLong_AsDouble(item);
      if (in->values[i] == -1.0 && PyErr_Occurred()) { PyErr_Clear(); return 0; }
    } else return 0;
  }
  return 1;
}

/* 1: `o` is a native float64 1-D array of `size` entries, read into in->values; 0: it is not. */
static int shape_ok(const Slot *slot, PyObject *o, Input *in) {
  Py_buffer view;
  int ok;
  if (PyList_CheckExact(o) || PyTuple_CheckExact(o)) return sequence_ok(slot, o, in);
#ifdef SYMKF_NUMPY
  if (PyArray_CheckExact(o)) {
    PyArrayObject *a = (PyArrayObject *) o;
    if (PyArray_TYPE(a) != NPY_DOUBLE || !PyArray_ISNOTSWAPPED(a) || PyArray_NDIM(a) != 1 ||
        PyArray_DIM(a, 0) != slot->size) return 0;
    gather(in, PyArray_BYTES(a), PyArray_STRIDE(a, 0), slot->size);
    return 1;
  }
#endif
  if (PyObject_GetBuffer(o, &view, PyBUF_STRIDES | PyBUF_FORMAT) != 0) {
    PyErr_Clear();
    return 0;
  }
  ok = view.ndim == 1 && view.shape[0] == slot->size && view.itemsize == 8 && native_double(view.format);
  if (ok) gather(in, (const char *) view.buf, view.strides[0], slot->size);
  PyBuffer_Release(&view);
  return ok;
}

/* Phase 1 for one slot: 1 if `o` fits (or is an accepted None), 0 if Python must answer.
   Never writes a buffer. A CHECK_USED slot's values are checked afterwards (used_ok). */
static int accept(const Slot *slot, PyObject *o, Input *in) {
  in->given = 0;
  if (o == Py_None) return slot->if_none != NONE_DECLINE;
  if (slot->if_none == ABSENT || !shape_ok(slot, o, in)) return 0;
  in->given = 1;
  return checked(in->values, slot->size, slot->check);
}

/* Phase 1 for a CHECK_USED slot (after every slot was accepted): finite where the mask uses the
   component. The mask (n entries, one per component, or one for the whole measurement) is the
   call's, or for None all ones (NONE_ONES) or the held buffer (NONE_KEEP); a component is used
   where its mask entry is 1 (> 0.5 for the held buffer, as the kernel reads it). */
static int used_ok(const Step *self, int s, const Input *inputs) {
  const Slot *slot = &self->slots[s], *mask = self->mask_slot < 0 ? NULL : &self->slots[self->mask_slot];
  const double *z = inputs[s].values, *m;
  Py_ssize_t i;
  if (!inputs[s].given) return 1;
  if (mask == NULL || mask->size == 0) return checked(z, slot->size, CHECK_FINITE);
  m = inputs[self->mask_slot].given ? inputs[self->mask_slot].values : mask->if_none == NONE_KEEP ? mask->dst : NULL;
  if (m == NULL) return mask->if_none == NONE_ONES ? checked(z, slot->size, CHECK_FINITE) : 1;
  for (i = 0; i < slot->size; ++i)
    if (m[mask->size == slot->size ? i : 0] > 0.5 && !isfinite(z[i])) return 0;
  return 1;
}

static void write_slot(const Slot *slot, const Input *in) {
  Py_ssize_t i;
  if (in->given) {
    for (i = 0; i < slot->size; ++i) slot->dst[i] = in->values[i];
  } else if (slot->if_none == NONE_ONES || slot->if_none == NONE_ZEROS) {
    for (i = 0; i < slot->size; ++i) slot->dst[i] = slot->if_none == NONE_ONES ? 1.0 : 0.0;
  }
}

/* The trusted kernel on the bound buffers; on success the step's inputs are kept for the replay of
   its diagnostics (on failure nothing is: the replay buffers keep the last successful step's). */
static int trusted_step(Step *self) {
  double carried[MAX_SAVED], *at = carried;
  const Save *save, *inputs = self->saves + self->n_carried, *end = self->saves + self->n_saves;
  Py_ssize_t j;
  int code;
  for (save = self->saves; save < inputs; at += save->n, ++save) memcpy(at, save->from, (size_t) save->n * sizeof(double));
  code = self->trusted(self->trusted_args);
  if (code != 0 && code != self->gated) return code;
  for (save = self->saves, at = carried; save < inputs; at += save->n, ++save)
    memcpy(save->into, at, (size_t) save->n * sizeof(double));
  for (; save < end; ++save)                  /* a few entries each (t, dt, z, ...): no memcpy call */
    for (j = 0; j < save->n; ++j) save->into[j] = save->from[j];
  *self->stale = 1.0;
  ++self->trusted_calls;
  return code;
}

/* Whether a step's t is the filter's time `clock`: within CLOCK_DT_RTOL of dt plus CLOCK_ULPS
   roundings of the larger time (symkf/runtime/contract.py on_clock, the same numbers); a call
   that is not is declined, and the Python path says by how much and how to move the clock. */
#define CLOCK_DT_RTOL 1e-6
#define CLOCK_ULPS 16.0
static int on_clock(double t, double clock, double dt) {
  double scale = fmax(1.0, fmax(fabs(t), fabs(clock)));
  return fabs(t - clock) <= CLOCK_DT_RTOL * dt + CLOCK_ULPS * DBL_EPSILON * scale;
}

/* The checks, copies and kernel call of one step (argv: t, dt, then one object per slot): the
   status code (a new int), or None having written nothing (see the top of this file). */
static PyObject *step_run(Step *self, PyObject *const *argv) {
  Input inputs[MAX_SLOTS];
  int i, code;
  double t, dt;
  if (argv[0] == Py_None && self->clock != NULL) t = *self->clock;
  else if (!finite_float(argv[0], &t)) Py_RETURN_NONE;
  if (!finite_float(argv[1], &dt) || !(dt > 0.0)) Py_RETURN_NONE;
  if (self->clock != NULL && !on_clock(t, *self->clock, dt)) Py_RETURN_NONE;
  for (i = 0; i < self->n_slots; ++i) if (!accept(&self->slots[i], argv[2 + i], &inputs[i])) Py_RETURN_NONE;
  for (i = 0; i < self->n_slots; ++i)
    if (self->slots[i].check == CHECK_USED && !used_ok(self, i, inputs)) Py_RETURN_NONE;
  if (self->t != NULL) *self->t = t;
  if (self->dt != NULL) *self->dt = dt;
  for (i = 0; i < self->n_slots; ++i) write_slot(&self->slots[i], &inputs[i]);
  code = self->trusted != NULL && *self->own != 0.0 ? trusted_step(self) : self->kernel(self->args);
  if (code != 0 && code != self->gated) Py_RETURN_NONE;   /* state unchanged: Python raises it */
  if (self->trusted != NULL && *self->own == 0.0) {         /* a checked step: y, S are its own */
    *self->own = 1.0;
    *self->stale = 0.0;
  }
  if (self->clock != NULL) *self->clock = t + dt;
  ++self->calls;
  return PyLong_FromLong(code);
}

static PyObject *step_call(PyObject *callable, PyObject *const *argv, size_t nargsf, PyObject *kwnames) {
  Step *self = (Step *) callable;
  if (kwnames != NULL || PyVectorcall_NARGS(nargsf) != 2 + self->n_slots) {
    PyErr_Format(PyExc_TypeError, "Step expects %d positional arguments (t, dt, %d arrays)",
                 2 + self->n_slots, self->n_slots);
    return NULL;
  }
  return step_run(self, argv);
}

static void *address(PyObject *o) {
  return o == Py_None ? NULL : PyLong_AsVoidPtr(o);
}

/* The optional trusted part of a Step: None, or (kernel, args, own, stale, saves), addresses as
   ints, saves a tuple of (from, into, n, carried). 1 on success, 0 with an exception set. */
static int set_trusted(Step *self, PyObject *trusted) {
  PyObject *kernel, *args, *own, *stale, *saves;
  Py_ssize_t i, total = 0;
  if (trusted == Py_None) return 1;
  if (!PyArg_ParseTuple(trusted, "OOOOO!", &kernel, &args, &own, &stale, &PyTuple_Type, &saves)) return 0;
  if (PyTuple_GET_SIZE(saves) > MAX_SAVES) {
    PyErr_Format(PyExc_ValueError, "Step: at most %d saved buffers", MAX_SAVES);
    return 0;
  }
  self->trusted = (kernel_v) address(kernel);
  self->trusted_args = (double *const *) address(args);
  self->own = (double *) address(own);
  self->stale = (double *) address(stale);
  self->n_saves = (int) PyTuple_GET_SIZE(saves);
  for (i = 0; i < self->n_saves; ++i) {
    PyObject *from, *into;
    Save *save = &self->saves[i];
    if (!PyArg_ParseTuple(PyTuple_GET_ITEM(saves, i), "OOni", &from, &into, &save->n, &save->carried)) return 0;
    save->from = (const double *) address(from);
    save->into = (double *) address(into);
    total += save->carried ? save->n : 0;
    self->n_carried += save->carried != 0;
    if (save->n < 0 || save->from == NULL || save->into == NULL || (save->carried && self->n_carried <= i)) break;
  }
  if (PyErr_Occurred()) return 0;
  if (i < self->n_saves || total > MAX_SAVED || self->trusted == NULL || self->trusted_args == NULL ||
      self->own == NULL || self->stale == NULL) {
    PyErr_Format(PyExc_ValueError, "Step: bad trusted part (kernel, args, own, stale addresses; saves of "
                 "(from, into, n >= 0, carried), the carried first, %d carried entries in all at most)", MAX_SAVED);
    return 0;
  }
  return 1;
}

/* Step(kernel, args, t, dt, clock, slots, gated, keep_alive[, trusted]): addresses as ints (t, dt,
   clock may be None); slots a tuple of (address, size, if_none, check); gated the status code of a
   gated update; keep_alive holds the buffers those addresses point into; trusted: set_trusted. */
static PyObject *step_new(PyTypeObject *type, PyObject *a, PyObject *kw) {
  PyObject *kernel, *args, *t, *dt, *clock, *slots, *keep_alive, *trusted = Py_None;
  int gated;
  Step *self;
  Py_ssize_t i;
  if (kw != NULL && PyDict_GET_SIZE(kw)) {
    PyErr_SetString(PyExc_TypeError, "Step takes positional arguments only");
    return NULL;
  }
  if (!PyArg_ParseTuple(a, "OOOOOO!iO|O", &kernel, &args, &t, &dt, &clock, &PyTuple_Type, &slots, &gated,
                        &keep_alive, &trusted)) return NULL;
  if (PyTuple_GET_SIZE(slots) > MAX_SLOTS) {
    PyErr_Format(PyExc_ValueError, "Step: at most %d array arguments", MAX_SLOTS);
    return NULL;
  }
  self = (Step *) type->tp_alloc(type, 0);
  if (self == NULL) return NULL;
  self->vectorcall = step_call;
  self->kernel = (kernel_v) address(kernel);
  self->args = (double *const *) address(args);
  self->t = (double *) address(t);
  self->dt = (double *) address(dt);
  self->clock = (double *) address(clock);
  self->gated = gated;
  self->calls = 0;
  self->mask_slot = -1;
  self->n_slots = (int) PyTuple_GET_SIZE(slots);
  for (i = 0; i < PyTuple_GET_SIZE(slots); ++i) {
    Slot *s = &self->slots[i];
    PyObject *dst;
    if (!PyArg_ParseTuple(PyTuple_GET_ITEM(slots, i), "Onii", &dst, &s->size, &s->if_none, &s->check)) break;
    s->dst = (double *) address(dst);
    if (s->size < 0 || s->size > MAX_SIZE || s->if_none < NONE_KEEP || s->if_none > ABSENT || (s->size > 0 && s->dst == NULL)
        || s->check < CHECK_FINITE || s->check > CHECK_USED || (s->check == CHECK_MASK && self->mask_slot >= 0)) {
      PyErr_SetString(PyExc_ValueError, "Step: bad slot (address, 0 <= size <= 64, if_none 0..4, check 0..2, one mask)");
      break;
    }
    if (s->check == CHECK_MASK) self->mask_slot = (int) i;
  }
  if (!PyErr_Occurred()) set_trusted(self, trusted);
  if (PyErr_Occurred() || self->kernel == NULL || self->args == NULL) {
    if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "Step: kernel and args addresses are required");
    Py_DECREF(self);
    return NULL;
  }
  Py_INCREF(keep_alive);
  self->keep_alive = keep_alive;
  return (PyObject *) self;
}

static int step_traverse(Step *self, visitproc visit, void *arg) {
  Py_VISIT(self->keep_alive);
  return 0;
}

static int step_clear(Step *self) {
  Py_CLEAR(self->keep_alive);
  return 0;
}

static void step_dealloc(Step *self) {
  PyObject_GC_UnTrack(self);
  step_clear(self);
  Py_TYPE(self)->tp_free((PyObject *) self);
}

static PyMemberDef step_members[] = {
  {"calls", T_PYSSIZET, offsetof(Step, calls), READONLY, "calls that took the fast path and succeeded"},
  {"trusted_calls", T_PYSSIZET, offsetof(Step, trusted_calls), READONLY, "of those, calls of the trusted kernel"},
  {NULL, 0, 0, 0, NULL},
};

static PyTypeObject StepType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "_symkf_fastcall.Step",
  .tp_doc = "One bound filter step: Step(kernel, args, t, dt, clock, slots, gated, keep_alive[, trusted])(t, dt, *arrays) -> int | None",
  .tp_members = step_members,
  .tp_basicsize = sizeof(Step),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_HAVE_VECTORCALL,
  .tp_new = step_new,
  .tp_dealloc = (destructor) step_dealloc,
  .tp_traverse = (traverseproc) step_traverse,
  .tp_clear = (inquiry) step_clear,
  .tp_vectorcall_offset = offsetof(Step, vectorcall),
  .tp_call = PyVectorcall_Call,
};

/* ---- Method: a filter's step method whose plain calls run no Python frame ----
 *
 * Set on a filter as its `step` attribute (symkf/runtime/fastcall.py: method()). Called exactly as
 * the Python method (positional and keyword arguments, by the method's parameter names), it puts
 * the arguments in its Step's order (t, dt, arrays) and runs the Step. Anything else goes to the
 * Python method, bound, with the very same arguments: a call the Step declines, a `nan` other than
 * "raise", a measurement that is not a str with a fast path, a missing required argument, an
 * unknown or repeated keyword, too many arguments. So this adds no rule either: the Python method
 * answers every call it does not take, with the Python method's own errors.
 */
#define MAX_PARAMS 12

static PyObject *raise_string;   /* "raise", the `nan` policy the fast path implements */

typedef struct {
  PyObject_HEAD
  vectorcallfunc vectorcall;
  PyObject *fallback;        /* the Python method, bound to the filter */
  PyObject *names;           /* tuple of its parameter names (after self) */
  int n_params, required;    /* the first `required` parameters have no default */
  int nan_index;             /* the `nan` parameter (absent or "raise"), -1 if none */
  int select_index;          /* the measurement's name (absent or None: the default Step), -1 if none */
  PyObject *steps;           /* dict: measurement -> Step (select_index >= 0), else None */
  PyObject *last_name;       /* the last name a call selected a Step by (held, so that its address is
                                not reused) and that Step (borrowed from steps) */
  PyObject *last_step;
  PyObject *default_step;    /* a Step, or None: a call must name its measurement */
  int n_args;                /* 2 + the Steps' slot count */
  int arguments[2 + MAX_SLOTS];  /* per Step argument, the parameter that gives it (-1: None) */
  PyObject *result;          /* returned on success instead of the status code (None: the code) */
  Py_ssize_t calls;          /* calls it took */
  PyObject *kwnames;         /* the keyword names of the last call with keywords (a call site passes
                                the same tuple every time) and their parameters: */
  int kw_index[MAX_PARAMS];
} Method;

static int parameter(const Method *self, PyObject *name) {
  Py_ssize_t j;
  for (j = 0; j < self->n_params; ++j) if (PyTuple_GET_ITEM(self->names, j) == name) return (int) j;
  for (j = 0; j < self->n_params; ++j)
    if (PyUnicode_Compare(PyTuple_GET_ITEM(self->names, j), name) == 0) return (int) j;
  PyErr_Clear();
  return -1;
}

/* The Step a call selects (borrowed), or NULL: the Python method decides. */
static Step *selected(Method *self, PyObject *const *values) {
  PyObject *name, *step;
  if (self->select_index < 0 || values[self->select_index] == NULL || values[self->select_index] == Py_None)
    return self->default_step == Py_None ? NULL : (Step *) self->default_step;   /* None: a name is required */
  name = values[self->select_index];
  if (name == self->last_name) return (Step *) self->last_step;      /* a call site's literal: the same object */
  if (!PyUnicode_CheckExact(name)) return NULL;
  step = PyDict_GetItemWithError(self->steps, name);
  if (step == NULL) {
    PyErr_Clear();
    return NULL;
  }
  Py_INCREF(name);
  Py_XSETREF(self->last_name, name);
  self->last_step = step;
  return (Step *) step;
}

static PyObject *method_call(PyObject *callable, PyObject *const *args, size_t nargsf, PyObject *kwnames) {
  Method *self = (Method *) callable;
  Py_ssize_t nargs = PyVectorcall_NARGS(nargsf), nkw = kwnames == NULL ? 0 : PyTuple_GET_SIZE(kwnames), i;
  PyObject *values[MAX_PARAMS] = {NULL}, *argv[2 + MAX_SLOTS], *nan, *code;
  Step *step;
  if (nargs > self->n_params || nkw > MAX_PARAMS) goto python;
  for (i = 0; i < nargs; ++i) values[i] = args[i];
  if (nkw > 0 && kwnames != self->kwnames) {           /* a new call site: look its names up once */
    Py_CLEAR(self->kwnames);
    for (i = 0; i < nkw; ++i) if ((self->kw_index[i] = parameter(self, PyTuple_GET_ITEM(kwnames, i))) < 0) goto python;
    Py_INCREF(kwnames);
    self->kwnames = kwnames;
  }
  for (i = 0; i < nkw; ++i) {
    int j = self->kw_index[i];
    if (values[j] != NULL) goto python;
    values[j] = args[nargs + i];
  }
  for (i = 0; i < self->required; ++i) if (values[i] == NULL) goto python;
  nan = self->nan_index < 0 ? NULL : values[self->nan_index];
  if (nan != NULL && nan != raise_string && !(PyUnicode_CheckExact(nan) && PyUnicode_Compare(nan, raise_string) == 0))
    goto python;
  step = selected(self, values);
  if (step == NULL) goto python;
  for (i = 0; i < self->n_args; ++i) {
    int j = self->arguments[i];
    argv[i] = j < 0 || values[j] == NULL ? Py_None : values[j];
  }
  code = step_run(step, argv);
  if (code == NULL) return NULL;
  if (code != Py_None) {
    ++self->calls;
    if (self->result == Py_None) return code;
    Py_DECREF(code);
    Py_INCREF(self->result);
    return self->result;
  }
  Py_DECREF(code);
python:
  return PyObject_Vectorcall(self->fallback, args, nargsf, kwnames);
}

static int same_slots(PyObject *step, int n_slots) {
  return PyObject_TypeCheck(step, &StepType) && ((Step *) step)->n_slots == n_slots;
}

/* Method(fallback, names, required, nan_index, select_index, steps, default_step, arguments, result). */
static PyObject *method_new(PyTypeObject *type, PyObject *a, PyObject *kw) {
  PyObject *fallback, *names, *steps, *default_step, *arguments, *result, *key, *value, *shape;
  int required, nan_index, select_index, n_slots;
  Py_ssize_t i, pos = 0;
  Method *self;
  if (kw != NULL && PyDict_GET_SIZE(kw)) {
    PyErr_SetString(PyExc_TypeError, "Method takes positional arguments only");
    return NULL;
  }
  if (!PyArg_ParseTuple(a, "OO!iiiOOO!O", &fallback, &PyTuple_Type, &names, &required, &nan_index, &select_index,
                        &steps, &default_step, &PyTuple_Type, &arguments, &result)) return NULL;
  shape = default_step;                 /* None: every call names its Step (the slots of any of them) */
  if (default_step == Py_None && select_index >= 0 && PyDict_Check(steps) && PyDict_GET_SIZE(steps) > 0)
    PyDict_Next(steps, &pos, &key, &shape);
  pos = 0;
  n_slots = PyObject_TypeCheck(shape, &StepType) ? ((Step *) shape)->n_slots : -1;
  if (!PyCallable_Check(fallback) || n_slots < 0 || PyTuple_GET_SIZE(names) > MAX_PARAMS || required < 0 ||
      required > PyTuple_GET_SIZE(names) || nan_index >= PyTuple_GET_SIZE(names) ||
      select_index >= PyTuple_GET_SIZE(names) || (select_index >= 0) != PyDict_Check(steps) ||
      PyTuple_GET_SIZE(arguments) != 2 + n_slots) {
    PyErr_SetString(PyExc_ValueError, "Method: bad arguments (fallback, names, required, nan_index, select_index, "
                    "steps, default_step, arguments, result)");
    return NULL;
  }
  for (i = 0; i < PyTuple_GET_SIZE(names); ++i)
    if (!PyUnicode_CheckExact(PyTuple_GET_ITEM(names, i))) {
      PyErr_SetString(PyExc_TypeError, "Method: parameter names must be str");
      return NULL;
    }
  while (select_index >= 0 && PyDict_Next(steps, &pos, &key, &value))
    if (!PyUnicode_CheckExact(key) || !same_slots(value, n_slots)) {
      PyErr_SetString(PyExc_ValueError, "Method: steps maps names (str) to Steps of the default Step's slots");
      return NULL;
    }
  self = (Method *) type->tp_alloc(type, 0);
  if (self == NULL) return NULL;
  self->vectorcall = method_call;
  self->n_params = (int) PyTuple_GET_SIZE(names);
  self->required = required;
  self->nan_index = nan_index;
  self->select_index = select_index;
  self->n_args = 2 + n_slots;
  for (i = 0; i < self->n_args; ++i) {
    long j = PyLong_AsLong(PyTuple_GET_ITEM(arguments, i));
    if (j < -1 || j >= self->n_params) {
      if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "Method: an argument's parameter index is out of range");
      Py_DECREF(self);
      return NULL;
    }
    self->arguments[i] = (int) j;
  }
  self->steps = select_index >= 0 ? PyDict_Copy(steps) : (Py_INCREF(Py_None), Py_None);
  if (self->steps == NULL) {
    Py_DECREF(self);
    return NULL;
  }
  Py_INCREF(fallback);
  self->fallback = fallback;
  Py_INCREF(names);
  self->names = names;
  Py_INCREF(default_step);
  self->default_step = default_step;
  Py_INCREF(result);
  self->result = result;
  return (PyObject *) self;
}

static int method_traverse(Method *self, visitproc visit, void *arg) {
  Py_VISIT(self->fallback);
  Py_VISIT(self->names);
  Py_VISIT(self->steps);
  Py_VISIT(self->default_step);
  Py_VISIT(self->result);
  Py_VISIT(self->kwnames);
  Py_VISIT(self->last_name);
  return 0;
}

static int method_clear(Method *self) {
  Py_CLEAR(self->fallback);
  Py_CLEAR(self->names);
  Py_CLEAR(self->steps);
  Py_CLEAR(self->default_step);
  Py_CLEAR(self->result);
  Py_CLEAR(self->kwnames);
  Py_CLEAR(self->last_name);
  return 0;
}

static void method_dealloc(Method *self) {
  PyObject_GC_UnTrack(self);
  method_clear(self);
  Py_TYPE(self)->tp_free((PyObject *) self);
}

static PyMemberDef method_members[] = {
  {"calls", T_PYSSIZET, offsetof(Method, calls), READONLY, "calls the method took in C (no Python frame)"},
  {"__wrapped__", T_OBJECT, offsetof(Method, fallback), READONLY, "the Python method (its signature and docs)"},
  {NULL, 0, 0, 0, NULL},
};

static PyTypeObject MethodType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "_symkf_fastcall.Method",
  .tp_doc = "A filter's step method with its fast path in C; see __wrapped__ for its parameters and docs.",
  .tp_members = method_members,
  .tp_basicsize = sizeof(Method),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_HAVE_VECTORCALL,
  .tp_new = method_new,
  .tp_dealloc = (destructor) method_dealloc,
  .tp_traverse = (traverseproc) method_traverse,
  .tp_clear = (inquiry) method_clear,
  .tp_vectorcall_offset = offsetof(Method, vectorcall),
  .tp_call = PyVectorcall_Call,
};

static struct PyModuleDef module = {
  PyModuleDef_HEAD_INIT, "_symkf_fastcall", "symkf's checked fast path for one filter step.", -1, NULL,
};

PyMODINIT_FUNC PyInit__symkf_fastcall(void) {
  PyObject *m;
#ifdef SYMKF_NUMPY
  import_array();
#endif
  if (PyType_Ready(&StepType) < 0 || PyType_Ready(&MethodType) < 0) return NULL;
  raise_string = PyUnicode_InternFromString("raise");
  if (raise_string == NULL) return NULL;
  m = PyModule_Create(&module);
  if (m == NULL) return NULL;
  Py_INCREF(&StepType);
  if (PyModule_AddObject(m, "Step", (PyObject *) &StepType) < 0) {
    Py_DECREF(&StepType);
    Py_DECREF(m);
    return NULL;
  }
  Py_INCREF(&MethodType);
  if (PyModule_AddObject(m, "Method", (PyObject *) &MethodType) < 0) {
    Py_DECREF(&MethodType);
    Py_DECREF(m);
    return NULL;
  }
  PyModule_AddIntConstant(m, "MAX_SIZE", MAX_SIZE);
  PyModule_AddIntConstant(m, "MAX_SAVES", MAX_SAVES);
  PyModule_AddIntConstant(m, "MAX_SAVED", MAX_SAVED);
  PyModule_AddIntConstant(m, "NONE_KEEP", NONE_KEEP);
  PyModule_AddIntConstant(m, "NONE_ONES", NONE_ONES);
  PyModule_AddIntConstant(m, "NONE_ZEROS", NONE_ZEROS);
  PyModule_AddIntConstant(m, "NONE_DECLINE", NONE_DECLINE);
  PyModule_AddIntConstant(m, "ABSENT", ABSENT);
  PyModule_AddIntConstant(m, "CHECK_FINITE", CHECK_FINITE);
  PyModule_AddIntConstant(m, "CHECK_MASK", CHECK_MASK);
  PyModule_AddIntConstant(m, "CHECK_USED", CHECK_USED);
  return m;
}
