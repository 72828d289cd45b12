"""BLAS threads while stepping.

A step multiplies many small matrices (cubature and coupling GEMMs of a few hundred rows
by tens of columns). Multithreaded OpenBLAS gains little there on an idle machine and
loses badly on a shared one: its worker threads spin and wait for cores that other
processes (the rest of a co-simulation) hold. armadillo_class at load average 5.7 on 2
cores, step median: 287-299 ms with 2 BLAS threads, 19-32 ms with 1 (same run, see the
session note). So a reduced model steps with `model.blas_threads` BLAS threads ("auto": 1)
and the library's setting is left alone everywhere else (precompute keeps its threads). A
full-space model keeps MKL's threads while stepping ("auto"): its sparse factorisation
(MKL PARDISO, which threadpoolctl also counts as BLAS) took 9.7 s instead of 5.4 s on
armadillo_class's 176K DOFs with one thread. Its other BLAS (OpenBLAS here) gets one
thread: it multiplies the contact working set's columns (a Gram matrix of 375 x 90 on
grasp_lift), where two threads gave 14-24 ms spikes against 0.2-0.3 ms at load 2.3 when
numpy was imported before mdss_ros (which then cannot set OPENBLAS_NUM_THREADS). numba's
own pool is not affected.
"""
import contextlib


class BlasThreads:
    """Context manager factory: `with BlasThreads(1)(): ...` limits every BLAS library
    loaded in the process to n threads inside the block, except those whose threadpoolctl
    internal_api is in skip (e.g. ("mkl",)). n = None leaves them alone.
    The library list is read on first use (after numpy/scipy are loaded). It talks to
    the libraries' controllers directly: threadpoolctl's `limit()` re-reads every
    library's info on each call, about 75 us, a quarter of a small model's step."""

    def __init__(self, n, skip=()):
        self.n = n
        self.skip = tuple(skip)       # threadpoolctl internal_api names left alone (e.g. "mkl")
        self._libs = None

    def __call__(self):
        if self.n is None:
            return _NULL
        if self._libs is None:
            try:
                from threadpoolctl import ThreadpoolController
            except ImportError:          # optional at run time: stepping still works
                self.n = None
                return _NULL
            self._libs = [_thread_calls(lib) for lib in
                          ThreadpoolController().select(user_api="blas").lib_controllers
                          if lib.internal_api not in self.skip]
        return _Limited(self._libs, self.n)


class _Limited:
    """One `with` block of BlasThreads: sets the libraries whose thread count differs from
    n, and restores those on exit. A class, not a @contextmanager generator, and the
    libraries' functions looked up once: Simulator.step and every surface read enter one,
    and the generator with threadpoolctl's per-call symbol lookups took 4.6-7 us of a
    0.23 ms step. A new object per block, so nested blocks and threads keep their own."""

    __slots__ = ("libs", "n", "changed")

    def __init__(self, libs, n):
        self.libs = libs        # [(get_num_threads, set_num_threads)]
        self.n = n
        self.changed = ()

    def __enter__(self):
        n = self.n
        changed = []
        for get, set_ in self.libs:
            old = get()
            if old != n:
                set_(n)
                changed.append((set_, old))
        self.changed = changed
        return self

    def __exit__(self, *exc_info):
        for set_, old in self.changed:
            set_(old)
        return False


def _thread_calls(lib):
    """(get_num_threads(), set_num_threads(n)) of a threadpoolctl controller: OpenBLAS's own
    C functions when the controller finds them (what its methods call, looked up on every
    call there), else its methods."""
    if getattr(lib, "internal_api", None) == "openblas":
        try:
            get = lib._get_symbol("openblas_get_num_threads")
            set_ = lib._get_symbol("openblas_set_num_threads")
        except Exception:          # a private helper of threadpoolctl: fall back
            get = set_ = None
        if get is not None and set_ is not None:
            return get, set_
    return lib.get_num_threads, lib.set_num_threads


_NULL = contextlib.nullcontext()


# ---------------------------------------------------------------------------------------
# numba kernels: threads only where the work pays for waking them
# ---------------------------------------------------------------------------------------
#: Work items (elements, vertices, samples) below which a kernel runs on one thread.
#: Waking numba's thread pool costs ~10-20 us of wall time per kernel launch; a reduced step
#: launches several, and on a 1-domain 12-DOF model they made the step 20 % slower than
#: the loops they replaced. warmup.py sets it to 0 once, so both variants get compiled.
SERIAL_BELOW = 2048


def serial_twin(kernel):
    """The numba kernel `kernel` (parallel=True) compiled again without threads (prange
    runs as range). It gets its own name, `<name>_serial`: numba's on-disk cache keys a
    kernel on its qualified name and source, not on the parallel flag, so the two
    variants would otherwise load each other's machine code."""
    import types
    from numba import njit
    f = kernel.py_func
    g = types.FunctionType(f.__code__, f.__globals__, f.__name__ + "_serial", f.__defaults__, f.__closure__)
    g.__qualname__ = f.__qualname__ + "_serial"
    g.__module__ = f.__module__
    g.__doc__ = f.__doc__
    return njit(cache=True)(g)


def pick(kernel, twin, n_items, weight=1):
    """kernel when n_items x weight >= SERIAL_BELOW, else its serial twin. weight: the work
    of one item relative to a vertex reconstruction (an element or a cubature sample with
    its material law is several)."""
    return kernel if n_items * weight >= SERIAL_BELOW else twin


def preload_kernels():
    """Load every kernel this process has imported (the mdss_ros modules in sys.modules)
    from numba's on-disk cache now, for every signature the cache holds, and return how
    many were loaded.

    numba loads a cached kernel on its first call, a few milliseconds each. A run whose
    body first touches a collider mid-run loaded about a dozen contact kernels at that
    step: hammock's first contact steps took 69 and 31 ms against a 2.4 ms median, six
    missed frames of a 90 Hz node. The node and `mdss run` call this before the first step
    (ros/driver.Driver.start), and `mdss bench` before its timed steps. Only entries the
    cache itself would serve are loaded: the index of a kernel whose source changed is
    empty, and an entry for another CPU or another version of the kernel's code is
    skipped, so nothing is compiled here. It reads numba's cache index, which is not a
    public interface: if that fails, nothing is preloaded and kernels load on first use
    as before."""
    import gc
    import sys
    from numba.core.registry import CPUDispatcher
    loaded = 0
    for name, module in list(sys.modules.items()):
        if module is None or not (name == "mdss_ros" or name.startswith("mdss_ros.")):
            continue
        for obj in list(vars(module).values()):
            if not isinstance(obj, CPUDispatcher) or obj._cache is None or obj.py_func.__module__ != name:
                continue
            try:
                codegen = obj.targetctx.codegen()
                here = obj._cache._index_key(None, codegen)[1:]       # (this CPU, this code)
                signatures = [key[0] for key in obj._cache._cache_file._load_index() if key[1:] == here]
            except Exception:             # numba's internals moved: load on first use instead
                continue
            for sig in signatures:
                if tuple(sig) not in obj.overloads:
                    obj.compile(sig)
                    loaded += 1
    # The loaded kernels are thousands of new long-lived objects: without a collection now,
    # they set off Python's next full (generation 2) collection mid-run, an 80 ms pause at
    # the caterpillar's step 421 (none in 600 steps without preloading, nor with this).
    gc.collect()
    return loaded
