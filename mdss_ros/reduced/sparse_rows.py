"""Contact constraint rows held as their entries (docs/method.md §14): a reduced body's
rows, frictionless or frictional, without full-space domains.

A contact row dt n^T J touches the columns of its corners' domains only: r_k modal
columns and six frame columns per corner (26 of the caterpillar's 208). Its dense (m,
n_gen) array (814 x 208 on the caterpillar's floor, every step) was mostly zeros: zeroed,
filled, normed and multiplied by the step whole. ContactRowEntries keeps each row's
entries in corner order, (cols, vals) (m, w) and count (m,), and gives what the contact
solve reads:

- C @ x (m,) and C^T lam (n,), in compiled passes over the entries, of all rows or of
  some (matvec_rows, rmatvec_rows);
- C[idx] (len(idx), n): dense rows, for the solves of the working set's rows. They are
  the same numbers, bit for bit, as the dense kernel they replaced (kept as the reference in
  test/test_sparse_rows.py): the same values added in the same order into zeros;
- norms (m,) of the rows, and take(sel), a subset of rows.

C @ x sums over a row's entries in corner order, where the dense product summed all n
columns in BLAS's order: the same value to round-off.
"""
import numpy as np
from numba import njit


@njit(cache=True)
def row_entries_kernel(dirs, rows, U, row_domain, R, c, xv, q_index, mask, frame_cols, row_of, dt,
                       cols, vals, count):
    """The entries of the contact rows: row row_of[i] r + j gets, for corner row
    i along its j-th direction, dt d^T J_i on its domain's modal columns (where mask) and
    frame columns, each appended as (column, value) in the order that kernel adds them.
    cols, vals (m r, w) written up to count (m r,), which starts at zero."""
    k, r = dirs.shape[0], dirs.shape[1]
    r_max = U.shape[2]
    for i in range(k):
        row = rows[i]
        dom = row_domain[row]
        ax = xv[i, 0] - c[dom, 0]
        ay = xv[i, 1] - c[dom, 1]
        az = xv[i, 2] - c[dom, 2]
        for j in range(r):
            d0, d1, d2 = dirs[i, j, 0], dirs[i, j, 1], dirs[i, j, 2]
            e0 = d0 * R[dom, 0, 0] + d1 * R[dom, 1, 0] + d2 * R[dom, 2, 0]
            e1 = d0 * R[dom, 0, 1] + d1 * R[dom, 1, 1] + d2 * R[dom, 2, 1]
            e2 = d0 * R[dom, 0, 2] + d1 * R[dom, 1, 2] + d2 * R[dom, 2, 2]
            o = row_of[i] * r + j
            n = count[o]
            for b in range(r_max):
                if mask[dom, b]:
                    cols[o, n] = q_index[dom, b]
                    vals[o, n] = dt * (e0 * U[row, 0, b] + e1 * U[row, 1, b] + e2 * U[row, 2, b])
                    n += 1
            if frame_cols[dom, 0] >= 0:
                cols[o, n] = frame_cols[dom, 0]
                vals[o, n] = dt * d0
                cols[o, n + 1] = frame_cols[dom, 1]
                vals[o, n + 1] = dt * d1
                cols[o, n + 2] = frame_cols[dom, 2]
                vals[o, n + 2] = dt * d2
                cols[o, n + 3] = frame_cols[dom, 3]
                vals[o, n + 3] = dt * (ay * d2 - az * d1)
                cols[o, n + 4] = frame_cols[dom, 4]
                vals[o, n + 4] = dt * (az * d0 - ax * d2)
                cols[o, n + 5] = frame_cols[dom, 5]
                vals[o, n + 5] = dt * (ax * d1 - ay * d0)
                n += 6
            count[o] = n


@njit(cache=True)
def _matvec(cols, vals, count, x, out):
    for o in range(count.shape[0]):
        acc = 0.0
        for t in range(count[o]):
            acc += vals[o, t] * x[cols[o, t]]
        out[o] = acc


@njit(cache=True)
def _rmatvec(cols, vals, count, lam, out):
    for o in range(count.shape[0]):
        lo = lam[o]
        if lo == 0.0:
            continue
        for t in range(count[o]):
            out[cols[o, t]] += vals[o, t] * lo


@njit(cache=True)
def _matvec_rows(cols, vals, count, idx, x, out):
    """out[a] = row idx[a] . x: _matvec on the rows idx, in the same order."""
    for a in range(idx.shape[0]):
        o = idx[a]
        acc = 0.0
        for t in range(count[o]):
            acc += vals[o, t] * x[cols[o, t]]
        out[a] = acc


@njit(cache=True)
def _rmatvec_rows(cols, vals, count, idx, lam, out):
    """out += sum_a lam[a] row idx[a]: _rmatvec on the rows idx, in the same order."""
    for a in range(idx.shape[0]):
        lo = lam[a]
        if lo == 0.0:
            continue
        o = idx[a]
        for t in range(count[o]):
            out[cols[o, t]] += vals[o, t] * lo


@njit(cache=True)
def _dense(cols, vals, count, idx, out):
    """out[a] += row idx[a]'s entries, in their order (out zeroed): the dense rows."""
    for a in range(idx.shape[0]):
        o = idx[a]
        for t in range(count[o]):
            out[a, cols[o, t]] += vals[o, t]


@njit(cache=True)
def _norms(cols, vals, count, scratch, out):
    """Euclidean norm of each row: its entries summed per column first (a face's corners in
    one domain share columns) in scratch (n,) zeros, which is left zeroed."""
    for o in range(count.shape[0]):
        for t in range(count[o]):
            scratch[cols[o, t]] += vals[o, t]
        acc = 0.0
        for t in range(count[o]):
            v = scratch[cols[o, t]]
            acc += v * v
            scratch[cols[o, t]] = 0.0           # counted once: later entries of the column read 0
        out[o] = np.sqrt(acc)


class ContactRowEntries:
    """C (m, n) of contact rows as their entries: cols, vals (m, w) int64 / float64, count
    (m,) int64 (entries of a row in cols[o, :count[o]]). See the module docstring."""

    __slots__ = ("cols", "vals", "count", "n")

    def __init__(self, cols, vals, count, n):
        self.cols, self.vals, self.count, self.n = cols, vals, count, int(n)

    @classmethod
    def build(cls, dirs, vrow, layout, R, c, xv, frame_cols, row_of, m, dt, n):
        """The rows dt d^T J of corner rows along dirs (k, r, 3) (row_entries_kernel's
        arguments): m contacts, n columns (n_gen)."""
        k, r = dirs.shape[:2]
        corners = 1 if k == m else np.bincount(row_of, minlength=m).max()     # corner rows per contact
        w = max(int(corners) * (layout.U.shape[2] + 6), 1)
        cols = np.zeros((m * r, w), dtype=np.int64)
        vals = np.zeros((m * r, w))
        count = np.zeros(m * r, dtype=np.int64)
        row_entries_kernel(np.ascontiguousarray(dirs), vrow, layout.U, layout.row_domain, R, c,
                           np.ascontiguousarray(xv), layout.q_index, layout.mask, frame_cols, row_of,
                           float(dt), cols, vals, count)
        return cls(cols, vals, count, n)

    @property
    def shape(self):
        return (len(self.count), self.n)

    def __len__(self):
        return len(self.count)

    def __matmul__(self, x):
        """C @ x for x (n,)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.ndim != 1:
            return self[np.arange(len(self.count))] @ x
        out = np.empty(len(self.count))
        _matvec(self.cols, self.vals, self.count, x, out)
        return out

    def rmatvec(self, lam):
        """C^T lam (n,) for lam (m,)."""
        out = np.zeros(self.n)
        _rmatvec(self.cols, self.vals, self.count, np.ascontiguousarray(lam, dtype=np.float64), out)
        return out

    def matvec_rows(self, idx, x):
        """C[idx] @ x (len(idx),) for integer indices idx, without take()'s copies: the
        same sums as take(idx) @ x."""
        out = np.empty(len(idx))
        _matvec_rows(self.cols, self.vals, self.count, np.ascontiguousarray(idx, dtype=np.int64),
                     np.ascontiguousarray(x, dtype=np.float64), out)
        return out

    def rmatvec_rows(self, idx, lam):
        """C[idx]^T lam (n,) for integer indices idx and lam (len(idx),): the same sums as
        take(idx).rmatvec(lam)."""
        out = np.zeros(self.n)
        _rmatvec_rows(self.cols, self.vals, self.count, np.ascontiguousarray(idx, dtype=np.int64),
                      np.ascontiguousarray(lam, dtype=np.float64), out)
        return out

    def __getitem__(self, idx):
        """Dense rows (len(idx), n) of integer indices idx (or a boolean mask over the rows)."""
        idx = np.atleast_1d(np.asarray(idx))
        if idx.dtype == bool:
            idx = np.flatnonzero(idx)
        idx = np.ascontiguousarray(idx, dtype=np.int64)
        out = np.zeros((len(idx), self.n))
        _dense(self.cols, self.vals, self.count, idx, out)
        return out

    def norms(self):
        out = np.empty(len(self.count))
        _norms(self.cols, self.vals, self.count, np.zeros(self.n), out)
        return out

    def stacked(self, other):
        """These rows, then other's (same n), as one ContactRowEntries padded to the wider."""
        w = max(self.cols.shape[1], other.cols.shape[1])

        def wide(a):
            return a if a.shape[1] == w else np.pad(a, ((0, 0), (0, w - a.shape[1])))
        return ContactRowEntries(np.vstack([wide(self.cols), wide(other.cols)]),
                                 np.vstack([wide(self.vals), wide(other.vals)]),
                                 np.concatenate([self.count, other.count]), self.n)

    def take(self, sel):
        """The rows sel (integer indices), as ContactRowEntries."""
        return ContactRowEntries(self.cols[sel], self.vals[sel], self.count[sel], self.n)
