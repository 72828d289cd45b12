"""Precompute cache on disk.

The reduced model's slow parts are built in stages, each stored under a key that hashes
everything the stage depends on (and the key of the stage before it):

    bases     mesh, material, pins, partition settings, modes, basis options, code
    cubature  bases key, training and cubature settings, dt, damping, coupling, code

so changing the cubature settings reuses the bases, and changing the mesh rebuilds all.
"code" is a hash of the source files of the precompute (their syntax tree without
comments and docstrings), so editing their code invalidates old entries and editing a
comment does not. A file is an .npz holding the arrays plus a JSON header (magic, stage, key,
SHA-256 of the arrays); a file that fails to load, has another key or a wrong checksum is
reported and rebuilt, never used.

The folder is $MDSS_CACHE_DIR, else ~/.cache/mdss_ros.
"""
import ast
import hashlib
import io
import json
import os
import uuid
import zipfile
from pathlib import Path

import numpy as np

MAGIC = "mdss_ros precompute v1"
# Source files each stage's result depends on: editing one rebuilds that stage (and the
# stages after it, whose keys include its key), not the ones before.
# "file.py::Class.method" names one function of a file that also does other things (the
# reduced model builds its stages in a few methods; its step code is not part of them).
# linear_solver.py: its PARDISO settings decide the round-off of every sparse solve of the
# build (shift-invert bases, the training run, the compliance); listed under bases, whose
# key every later stage includes, so entries built before its reproducible mode (issue 17)
# are rebuilt rather than mixed with new ones.
STAGE_CODE = {
    "bases": ["reduced/partition.py", "reduced/auto_domains.py", "reduced/bend_cuts.py",
              "model_build.py::training_load_cases", "model_build.py::bends_from_loads",
              "reduced/residual_compliance.py::RestStatics", "reduced/residual_compliance.py::six_supports",
              "reduced/modal_basis.py", "reduced/domains.py", "fem/materials.py", "fem/material_kernels.py",
              "fem/elements.py", "fem/assembly.py", "fem/statics.py", "linear_solver.py", "precompute.py",
              "reduced/reduced_model.py::ReducedModel.__init__"],
    "cubature": ["reduced/training.py", "reduced/cubature.py", "reduced/sampled_forces.py",
                 "fem/backward_euler.py", "precompute.py",
                 "reduced/reduced_model.py::ReducedModel._build_cubature",
                 "reduced/reduced_model.py::ReducedModel._restore_cubature",
                 "reduced/reduced_model.py::ReducedModel._build_interface_cubature",
                 "reduced/reduced_model.py::ReducedModel.training_simulation"],
    "contact_modes": ["reduced/contact_modes.py", "reduced/residual_compliance.py", "precompute.py"],
    "compliance": ["reduced/residual_compliance.py", "reduced/layout.py", "fem/force_model.py", "precompute.py",
                   "reduced/reduced_model.py::ReducedModel._build_compliance"],
}


def code_hash(stage="bases"):
    """SHA-256 (16 hex) of the source files a stage of the precompute depends on."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for item in STAGE_CODE[stage]:
        rel, _, name = item.partition("::")
        p = root / rel
        h.update(item.encode())
        # A renamed file or method must not hash as "missing" and keep serving stale caches.
        if not p.exists():
            raise RuntimeError(f"precompute.STAGE_CODE[{stage!r}] names {rel}, which does not exist: "
                               f"update STAGE_CODE to the module that now holds that code")
        fingerprint = _file_fingerprint(p, name or None)
        if fingerprint == b"missing":
            raise RuntimeError(f"precompute.STAGE_CODE[{stage!r}] names {item}, which {rel} no longer "
                               f"defines: update STAGE_CODE to where that code moved")
        h.update(fingerprint)
    return h.hexdigest()[:16]


_FINGERPRINTS = {}


def _file_fingerprint(path, name):
    """code_fingerprint of a file's source, remembered per process for the file's current
    (mtime, ctime, inode, size): parsing and dumping the syntax trees of a build's 26 stage
    sources took 1.1 s of a small model's 2.2 s build (cantilever at cell 0.05, 2 domains),
    on every build of a process (a test session, a study, a node that rebuilds)."""
    st = path.stat()
    # ctime and inode too: a copy that keeps the mtime (cp -p, rsync -t) changes them
    key = (str(path), st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_size, name)
    if key not in _FINGERPRINTS:
        _FINGERPRINTS[key] = code_fingerprint(path.read_text(), name)
    return _FINGERPRINTS[key]


def code_fingerprint(source, name=None):
    """The syntax tree of Python source without docstrings (comments are not in it), as
    bytes: a comment or docstring edit keeps it, any code edit changes it. name: a dotted
    path ("Class.method") to fingerprint one definition only (b"missing" if absent)."""
    tree = ast.parse(source)
    for part in (name.split(".") if name else []):
        tree = next((n for n in getattr(tree, "body", []) if isinstance(n, (ast.ClassDef, ast.FunctionDef))
                     and n.name == part), None)
        if tree is None:
            return b"missing"
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                    and isinstance(first.value.value, str)):
                node.body = node.body[1:] or [ast.Pass()]
    return ast.dump(tree, include_attributes=False).encode()


def cache_key(*parts):
    """Stable hash of nested parts: numpy arrays (dtype, shape, bytes), dicts, lists, scalars."""
    h = hashlib.sha256()

    def feed(x):
        if isinstance(x, np.ndarray):
            a = np.ascontiguousarray(x)
            h.update(f"nd{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        elif isinstance(x, dict):
            h.update(b"{")
            for k in sorted(x, key=str):
                feed(str(k))
                feed(x[k])
            h.update(b"}")
        elif isinstance(x, (list, tuple)):
            h.update(b"[")
            for v in x:
                feed(v)
            h.update(b"]")
        else:
            h.update(repr(x).encode())
            h.update(b";")

    for p in parts:
        feed(p)
    return h.hexdigest()[:24]


def _payload_digest(arrays):
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode())
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


class PrecomputeCache:
    """Folder of stage files. `events` records what happened (hit, miss, rebuilt-corrupt)."""

    def __init__(self, folder=None, enabled=True):
        self.folder = Path(folder or os.environ.get("MDSS_CACHE_DIR") or Path.home() / ".cache" / "mdss_ros")
        self.enabled = enabled
        self.events = []

    def path(self, stage, key):
        return self.folder / f"{stage}-{key}.npz"

    def load(self, stage, key):
        """(arrays dict, meta dict) or None. Bad files are reported in events and ignored."""
        if not self.enabled:
            return None
        p = self.path(stage, key)
        if not p.exists():
            self.events.append((stage, "miss", str(p)))
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                header = json.loads(bytes(z["__header__"]).decode())
                arrays = {k: z[k] for k in z.files if k != "__header__"}
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError, EOFError) as err:
            self.events.append((stage, "corrupt", f"{p}: {type(err).__name__}: {err}"))
            return None
        problem = None
        if header.get("magic") != MAGIC or header.get("stage") != stage:
            problem = "not an mdss_ros precompute file of this stage"
        elif header.get("key") != key:
            problem = f"written for other inputs (key {header.get('key')})"
        elif header.get("sha256") != _payload_digest(arrays):
            problem = "checksum mismatch"
        if problem:
            self.events.append((stage, "corrupt", f"{p}: {problem}"))
            return None
        self.events.append((stage, "hit", str(p)))
        return arrays, header.get("meta", {})

    def save(self, stage, key, arrays, meta=None):
        """Write atomically (temp file then rename) so a crash never leaves half a file."""
        if not self.enabled:
            return None
        self.folder.mkdir(parents=True, exist_ok=True)
        header = {"magic": MAGIC, "stage": stage, "key": key, "sha256": _payload_digest(arrays),
                  "meta": meta or {}}
        buf = io.BytesIO()
        np.savez(buf, __header__=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), **arrays)
        p = self.path(stage, key)
        # A temporary name of this writer's own: two runs building the same entry at once
        # (a cold cache shared by two nodes) both wrote KEY.tmp, the first rename took the
        # other's file away and the second writer's os.replace failed its build.
        # (Not mkstemp: its files are private to the user, the cache's keep the umask's mode.)
        tmp = p.with_name(f"{p.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp")
        try:
            tmp.write_bytes(buf.getvalue())
            os.replace(tmp, p)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        self.events.append((stage, "saved", str(p)))
        return p


def bases_cache_key(body, model_cfg, training_loads=None):
    """Key of the bases stage: mesh, material, pins, partition settings, modes, basis
    options, and the scene's training load cases when they place cuts
    (model_build.training_load_cases; None otherwise, which keys as before)."""
    mat = body.material
    cfg = model_cfg
    parts = [body.vertices, body.tets, mat.kind_id, mat.params, mat.density, body.pinned, cfg.get("domains"),
             cfg.get("full_space_domains"), cfg["modes"], cfg.get("basis") or {}]
    if training_loads is not None:
        parts.append([case.key() for case in training_loads])
    return cache_key("bases", code_hash("bases"), *parts)


def cubature_cache_key(bases_key, cubature_cfg, dt, alpha, beta, model_cfg):
    """Key of the cubature stage: the bases key plus training/cubature settings, dt, damping, coupling."""
    return cache_key("cubature", bases_key, code_hash("cubature"), cubature_cfg, float(dt), float(alpha),
                     float(beta), model_cfg.get("coupling") or {})


def contact_modes_cache_key(bases_key, settings, vertices):
    """The bases key once contact modes (settings: model.contact_modes) on the candidate
    vertices are added: what the later stages (cubature, compliance) key on."""
    return cache_key("contact_modes", bases_key, code_hash("contact_modes"), settings, np.asarray(vertices))


def compliance_cache_key(bases_key, vertices):
    """Key of the residual contact compliance: the bases key (mesh, material, pins,
    domains, modes) plus the candidate vertices."""
    return cache_key("compliance", bases_key, code_hash("compliance"), vertices)
