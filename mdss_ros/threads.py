"""BLAS threads while stepping.

A step multiplies many small matrices (cubature and coupling GEMMs of a few hundred rows
by tens of columns). Multithreaded OpenBLAS gains little there on an idle machine and
loses badly on a shared one: its worker threads spin and wait for cores that other
processes (the rest of a co-simulation) hold. armadillo_class at load average 5.7 on 2
cores, step median: 287-299 ms with 2 BLAS threads, 19-32 ms with 1 (same run, see the
session note). So a reduced model steps with `model.blas_threads` BLAS threads ("auto": 1)
and the library's setting is left alone everywhere else (precompute keeps its threads). A
full-space model keeps them while stepping too ("auto": the library's): its sparse
factorisation (MKL PARDISO, which threadpoolctl also counts as BLAS) took 9.7 s instead of
5.4 s on armadillo_class's 176K DOFs with one thread. numba's own pool is not affected.
"""
import contextlib


class BlasThreads:
    """Context manager factory: `with BlasThreads(1)(): ...` limits every BLAS library
    loaded in the process to n threads inside the block. n = None leaves them alone.
    The library list is read on first use (after numpy/scipy are loaded). It talks to
    the libraries' controllers directly: threadpoolctl's `limit()` re-reads every
    library's info on each call, about 75 us, a quarter of a small model's step."""

    def __init__(self, n):
        self.n = n
        self._libs = None

    def __call__(self):
        if self.n is None:
            return contextlib.nullcontext()
        if self._libs is None:
            try:
                from threadpoolctl import ThreadpoolController
            except ImportError:          # optional at run time: stepping still works
                self.n = None
                return contextlib.nullcontext()
            self._libs = ThreadpoolController().select(user_api="blas").lib_controllers
        return self._limited()

    @contextlib.contextmanager
    def _limited(self):
        saved = [lib.get_num_threads() for lib in self._libs]
        for lib, n in zip(self._libs, saved):
            if n != self.n:
                lib.set_num_threads(self.n)
        try:
            yield
        finally:
            for lib, n in zip(self._libs, saved):
                if n != self.n:
                    lib.set_num_threads(n)


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
