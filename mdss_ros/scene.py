"""Scene files (msg_scenes/*.yaml): load, apply overrides, validate.

A scene is a plain nested dict after loading, checked against SCHEMA: every key is
known, every value has the right kind, defaults are filled in. Errors name the file,
the dotted key and what is wrong, so a user can fix a scene without reading code.
"""
import copy
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import re

import yaml

from .errors import SceneError


class _SceneLoader(yaml.SafeLoader):
    """SafeLoader that also reads 1e5 and 1.0e7 as floats (YAML 1.1 wants 1.0e+7)."""


_SceneLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"""),
    list("-+0123456789"))


def read_yaml(text):
    """Parse YAML text the way scene and parameter files expect (1e5 is a float)."""
    return yaml.load(text, Loader=_SceneLoader)

# Leaf kinds: a type, a tuple of types, or a callable validator(value, where) -> value.
_NUM = (int, float)


def _vec3(value, where):
    if (not isinstance(value, (list, tuple)) or len(value) != 3
            or not all(isinstance(v, _NUM) and not isinstance(v, bool) for v in value)):
        raise SceneError(f"{where}: expected a list of 3 numbers, got {value!r}")
    return [float(v) for v in value]


def _positive(value, where):
    if not isinstance(value, _NUM) or isinstance(value, bool) or not value > 0:
        raise SceneError(f"{where}: expected a positive number, got {value!r}")
    return float(value)


def _nonneg(value, where):
    if not isinstance(value, _NUM) or isinstance(value, bool) or not value >= 0:
        raise SceneError(f"{where}: expected a number >= 0, got {value!r}")
    return float(value)


def _posint(value, where):
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise SceneError(f"{where}: expected an integer >= 1, got {value!r}")
    return value


def _nonneg_int(value, where):
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise SceneError(f"{where}: expected an integer >= 0, got {value!r}")
    return value


def _blas_threads(value, where):
    return value if value is None or value == "auto" else _posint(value, where)


def _choice(*options):
    def check(value, where):
        if value not in options:
            raise SceneError(f"{where}: expected one of {', '.join(map(repr, options))}, got {value!r}")
        return value
    return check


def _neighbours(value, where):
    if not isinstance(value, int) or isinstance(value, bool) or not 4 <= value <= 64:
        raise SceneError(f"{where}: expected an integer from 4 to 64 (the paper uses 16), got {value!r}")
    return value


def _support_scale(value, where):
    if not isinstance(value, _NUM) or isinstance(value, bool) or not 0.5 <= value <= 10.0:
        raise SceneError(f"{where}: expected a number from 0.5 to 10 (support radius / mean distance to "
                         f"the neighbours), got {value!r}")
    return float(value)


def _spacing(value, where):
    if value == "auto":
        return value
    if not isinstance(value, _NUM) or isinstance(value, bool) or not 0 < value < float("inf"):
        raise SceneError(f"{where}: expected 'auto' or a lattice spacing in metres (> 0), got {value!r}")
    return float(value)


def _substeps(value, where):
    return value if value == "auto" else _posint(value, where)


def _any(value, where):
    return value


def _bool(value, where):
    if not isinstance(value, bool):
        raise SceneError(f"{where}: expected true or false, got {value!r}")
    return value


# Nested dicts are sections; a section's "*" key validates any sub-key (user-named maps).
SCHEMA = {
    "name": (str, None),
    "description": (str, ""),
    "body": {
        "mesh": (dict, None),
        "material": (dict, None),
        "damping": {"alpha": (_nonneg, 0.0), "beta": (_nonneg, 0.0)},
        "mass": (_choice("lumped", "consistent"), "lumped"),
    },
    "pins": (list, []),
    "handles": (dict, {}),
    "colliders": (dict, {}),
    "model": {
        "kind": (_choice("full", "reduced", "meshless", "auto"), "full"),    # auto: resolved on load
        # full only: quadratic (10-node) tets, the bending-accurate truth (fem/quadratic.py)
        "element": (_choice("linear", "quadratic"), "linear"),
        # No domains given: the product places them (reduced/auto_domains.py; a body
        # without limbs gets one domain, "core").
        "domains": (_any, {"auto": True}),
        "modes": (_posint, 20),
        "cubature": (_any, {"samples": 0, "interface": "exact"}),
        "integrator": {
            "scheme": (_choice("one_step", "two_step", "backward_euler"), "one_step"),
            "dt": (_positive, 1.0 / 90.0),
            "newton_iterations": (_posint, 1),
            "tolerance": (_positive, 1e-6),
            "line_search": (_bool, True),
            "projection": (_choice("auto", "always", "never"), "auto"),
            # Reduced model: fictitious forces explicit (the papers') or implicit (Coriolis as
            # its exact flow, centrifugal stiffness in the system); the guard tries implicit.
            "fictitious": (_choice("explicit", "implicit"), "explicit"),
        },
        "solver": (_choice("auto", "pardiso", "cholmod", "splu"), "auto"),
        # BLAS threads while stepping (mdss_ros/threads.py); null = the library's default;
        # auto = 1 for reduced models (small GEMMs), the default for full-space ones (their
        # sparse factorisation gains from every core).
        "blas_threads": (_blas_threads, "auto"),
        "full_space_domains": (list, []),
        # Residual compliance of contact (reduced/residual_compliance.py, docs/method.md
        # §14.2): the local dent a subspace cannot make, on up to this many free surface
        # vertices nearest the colliders' paths in the scene; 0 turns it off.
        "contact_compliance": (_nonneg_int, 800),
        # Contact modes (reduced/contact_modes.py, docs/method.md §14.3): the alternatives the
        # residual compliance is measured against. Static (K^+ E_c) or local (a patch of
        # `radius` m, 0: 4 mean surface edges, held at its edge) answers to unit loads on the
        # `vertices` surface vertices nearest the colliders' paths, compressed to `count`
        # directions per domain and added to its modes. none: off.
        "contact_modes": {
            "kind": (_choice("none", "static", "local"), "none"),
            "vertices": (_posint, 50),
            "count": (_posint, 30),
            "radius": (_nonneg, 0.0),
        },
        "coupling": (dict, {"kind": "element"}),
        "basis": (dict, {}),
        "budget": (_any, {}),
        # model.kind: meshless (mdss_ros/meshless, docs/method.md §19): neighbours per node, support
        # radius in mean neighbour distances, volume term k_v in units of mu, time integrator and
        # RK4 sub-steps per step ("auto": from the highest frequency at rest); tet_barrier: the
        # material's compression barrier also on the tets of the mesh the nodes come from.
        "meshless": {
            "neighbours": (_neighbours, 16),
            "support_scale": (_support_scale, 2.0),
            "volume_stiffness": (_nonneg, 0.1),
            "integrator": (_choice("implicit", "rk4"), "implicit"),
            "substeps": (_substeps, "auto"),
            "integration": (_choice("consistent", "nodal"), "consistent"),
            "stabilisation": (_nonneg, 0.1),
            "volumes": (_choice("mesh", "support", "kernel"), "mesh"),
            "tet_barrier": (_bool, True),
            # nodes: the mesh's vertices, or a cubic lattice of edge `spacing` (m; auto: about
            # as many nodes as the mesh has vertices) clipped to the body (meshless/nodes.py)
            "nodes": (_choice("mesh", "lattice"), "mesh"),
            "spacing": (_spacing, "auto"),
        },
        # The stability guard (mdss_ros/guard.py): checks every step, rolls back and retries
        # a diverging one with more Newton iterations and sub-steps.
        "guard": {
            "enabled": (_bool, True),
            "energy_growth": (_positive, 0.1),
            "max_speed": (_positive, 1.0e3),
            "max_substeps": (_posint, 64),
            "newton_iterations": (_posint, 4),
            "inversion": (_bool, True),
            "energy_projection": (_bool, True),
            "untangle_after": (_nonneg_int, 10),
        },
    },
    "initial_velocity": {"linear": (_vec3, [0.0, 0.0, 0.0]), "angular": (_vec3, [0.0, 0.0, 0.0])},
    "gravity": (_vec3, [0.0, 0.0, -9.81]),
    "duration": (_positive, 2.0),
    "timeline": (list, []),
}


def _validate(section, schema, where, source):
    if not isinstance(section, dict):
        raise SceneError(f"{source}: {where or 'scene'}: expected a mapping, got {type(section).__name__}")
    unknown = sorted(set(section) - set(schema))
    if unknown:
        raise SceneError(f"{source}: unknown key{'s' if len(unknown) > 1 else ''} "
                         f"{', '.join((where + '.' if where else '') + k for k in unknown)} "
                         f"(allowed: {', '.join(sorted(schema))})")
    out = {}
    for key, rule in schema.items():
        dotted = f"{where}.{key}" if where else key
        if isinstance(rule, dict):
            out[key] = _validate(section.get(key, {}) or {}, rule, dotted, source)
            continue
        kind, default = rule
        if key not in section:
            if default is None:
                raise SceneError(f"{source}: missing required key {dotted}")
            out[key] = copy.deepcopy(default)
            continue
        value = section[key]
        if isinstance(kind, type) or isinstance(kind, tuple):
            if not isinstance(value, kind):
                raise SceneError(f"{source}: {dotted}: expected {getattr(kind, '__name__', kind)}, got {value!r}")
            out[key] = value
        else:
            out[key] = kind(value, f"{source}: {dotted}")
    return out


# The automatic model: what a scene with no `model` section (or `model: auto`, or
# `model.kind: auto`) gets. A reduced model with automatic domains (weighed against one
# domain), cubature at 10 samples per mode, and the modes the budget ladder finds for 5 %
# RMS surface error against full FEM over the scene's first second. Measured on
# msg_scenes/bunny.yaml (a user's OBJ, 18K tets, 1 domain): 8 modes, 4.9 % error, 0.3 ms
# a step against 196-251 ms for full FEM (README).
AUTOMATIC_MODEL = {"kind": "reduced", "domains": {"auto": True}, "modes": 16,
                   "cubature": {"samples": 160, "interface": "exact"}}
AUTOMATIC_BUDGET = {"max_error": 0.05, "probe": "exact", "domains": ["auto", 1]}


def automatic_model(model):
    """The model section of `model.kind: auto`: AUTOMATIC_MODEL under the keys the scene
    gives (they win). The budget ladder chooses the modes unless the scene fixes them
    (model.modes) or gives its own budget."""
    out = copy.deepcopy(AUTOMATIC_MODEL)
    out.update({k: copy.deepcopy(v) for k, v in model.items() if k != "kind"})
    given = model.get("budget")
    if "modes" not in model and not (isinstance(given, dict) and ("ms_per_step" in given or "max_error" in given)):
        # the automatic budget, with what the scene says of it (horizon, modes, probe); it
        # weighs the automatic domains against one domain unless the scene places them
        out["budget"] = dict(AUTOMATIC_BUDGET, **(given if isinstance(given, dict) else {}))
        if "domains" in model and not (isinstance(given, dict) and "domains" in given):
            del out["budget"]["domains"]
    return out


# model.budget (probed by mdss_ros/budget.py): its keys and the default ladder of modes
BUDGET_DEFAULT_MODES = (4, 6, 8, 12, 16, 24, 32)
BUDGET_KEYS = {"ms_per_step", "max_error", "horizon", "modes", "probe", "domains"}


def check_budget(budget, source="<scene>"):
    """Validate a model.budget mapping ({} = off); SceneError names what is wrong."""
    if budget in (None, {}):
        return {}
    where = f"{source}: model.budget"
    if not isinstance(budget, dict):
        raise SceneError(f"{where}: expected a mapping like {{ms_per_step: 5}} or {{max_error: 0.02}}, got {budget!r}")
    unknown = sorted(set(budget) - BUDGET_KEYS)
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {', '.join(unknown)} (allowed: {', '.join(sorted(BUDGET_KEYS))})")
    goals = [k for k in ("ms_per_step", "max_error") if k in budget]
    if len(goals) != 1:
        raise SceneError(f"{where}: give exactly one of ms_per_step or max_error, got {budget!r}")
    for k in ("ms_per_step", "max_error", "horizon"):
        v = budget.get(k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0):
            raise SceneError(f"{where}.{k}: expected a positive number, got {v!r}")
    if budget.get("probe", "scene") not in ("scene", "exact"):
        raise SceneError(f"{where}.probe: expected scene (probe each candidate as configured) or exact "
                         f"(probe with exact forces, then build the chosen one's cubature), got {budget['probe']!r}")
    if budget.get("probe") == "exact" and "ms_per_step" in budget:
        raise SceneError(f"{where}.probe: exact times candidates without their cubature, so it cannot "
                         f"choose for ms_per_step; use probe: scene")
    domains = budget.get("domains")
    if domains is not None:
        if (not isinstance(domains, (list, tuple)) or not domains or not all(
                d == "auto" or (isinstance(d, int) and not isinstance(d, bool) and d >= 1) for d in domains)):
            raise SceneError(f"{where}.domains: expected a list of auto and domain counts, like [auto, 1], "
                             f"got {domains!r}")
        if "ms_per_step" in budget and len(domains) > 1:
            raise SceneError(f"{where}.domains: weighing domain options needs an error goal (max_error); "
                             f"ms_per_step does not measure the error that tells them apart")
    modes = budget.get("modes", BUDGET_DEFAULT_MODES)
    if (not isinstance(modes, (list, tuple)) or not modes
            or not all(isinstance(m, int) and not isinstance(m, bool) and m >= 1 for m in modes)):
        raise SceneError(f"{where}.modes: expected a list of integers >= 1, got {modes!r}")
    return dict(budget, modes=sorted(set(modes)))


def apply_overrides(raw, overrides):
    """Set dotted keys ("model.modes": 10) in a raw scene dict, creating sections as needed."""
    raw = copy.deepcopy(raw)
    for dotted, value in (overrides or {}).items():
        node = raw
        parts = dotted.split(".")
        for p in parts[:-1]:
            nxt = node.get(p)
            if nxt is None:
                nxt = node[p] = {}
            if not isinstance(nxt, dict):
                raise SceneError(f"override {dotted}: {p} is not a section")
            node = nxt
        node[parts[-1]] = value
    return raw


def scene_search_path():
    """Folders searched for a scene given by name: cwd, the repo's msg_scenes, the share
    folder of every prefix on AMENT_PREFIX_PATH (a colcon workspace installs the scenes
    there, and `source install/setup.bash` puts it on that path), the venv's share."""
    here = Path(__file__).resolve().parent
    ament = [Path(p) / "share" / "mdss_ros" / "msg_scenes"
             for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return ([Path.cwd(), Path.cwd() / "msg_scenes", here.parent / "msg_scenes"] + ament
            + [Path(sys.prefix) / "share" / "mdss_ros" / "msg_scenes"])


def resolve_scene_path(name_or_path):
    p = Path(os.path.expanduser(str(name_or_path)))
    if p.is_file():
        return p
    candidates = [p.name] if p.suffix else [p.name + ".yaml", p.name]
    for folder in scene_search_path():
        for c in candidates:
            if (folder / c).is_file():
                return folder / c
    raise SceneError(f"scene {name_or_path!r} not found (looked in: "
                     f"{', '.join(str(f) for f in scene_search_path())})")


@dataclass
class Scene:
    """A validated scene. `data` is the full nested dict with defaults filled in;
    `source` names the file (for messages); `base_dir` resolves relative mesh paths."""

    data: dict
    source: str = "<dict>"
    base_dir: Path = field(default_factory=Path.cwd)
    warnings: list = field(default_factory=list)     # problems that do not stop a run (printed by mdss run)
    automatic_model: bool = False                    # the file gave no model section (automatic_model)

    def __getitem__(self, key):
        return self.data[key]

    @property
    def name(self):
        return self.data["name"]

    @property
    def dt(self):
        return self.data["model"]["integrator"]["dt"]


def load_scene(path_or_dict, overrides=None):
    """Load and validate a scene from a path, a scene name in msg_scenes/, or a dict.

    overrides: {"dotted.key": value} applied before validation.
    """
    if isinstance(path_or_dict, Scene):
        raw, source, base = copy.deepcopy(path_or_dict.data), path_or_dict.source, path_or_dict.base_dir
        was_automatic = path_or_dict.automatic_model
    elif isinstance(path_or_dict, dict):
        raw, source, base = path_or_dict, "<dict>", Path.cwd()
    else:
        path = resolve_scene_path(path_or_dict)
        source, base = str(path), path.parent
        try:
            raw = read_yaml(path.read_text())
        except yaml.YAMLError as err:
            raise SceneError(f"{path}: not valid YAML: {err}") from err
        if raw is None:
            raise SceneError(f"{path}: the file is empty")
    if not isinstance(raw, dict):
        raise SceneError(f"{source}: expected a mapping of scene sections, got {type(raw).__name__}")
    if raw.get("model") in (None, "auto"):
        raw = dict(raw, model={"kind": "auto"})
    raw = apply_overrides(raw, overrides)
    automatic = isinstance(raw.get("model"), dict) and raw["model"].get("kind") == "auto"
    if automatic:
        raw = dict(raw, model=automatic_model(raw["model"]))
    automatic = automatic or (isinstance(path_or_dict, Scene) and was_automatic
                              and raw["model"].get("kind") == "reduced")
    data = _validate(raw, SCHEMA, "", source)
    warnings = _check_sections(data, source)
    _check_body(data, source, Path(base))
    _check_colliders(data, source, Path(base))
    _check_model(data["model"], source)
    return Scene(data=data, source=source, base_dir=Path(base), warnings=warnings, automatic_model=automatic)


def _check_sections(data, source):
    """Checks needing more than one key; returns warnings (list of str)."""
    warnings = []
    data["model"]["budget"] = check_budget(data["model"]["budget"], source)
    for i, pin in enumerate(data["pins"]):
        if not isinstance(pin, dict):
            raise SceneError(f"{source}: pins[{i}]: expected a region mapping (box, sphere, plane, indices)")
    for name, region in data["handles"].items():
        if not isinstance(region, dict):
            raise SceneError(f"{source}: handles.{name}: expected a region mapping (box, sphere, plane, indices)")
    for i, ev in enumerate(data["timeline"]):
        if not isinstance(ev, dict) or "t" not in ev or "topic" not in ev:
            raise SceneError(f"{source}: timeline[{i}]: each event needs t and topic, got {ev!r}")
        if not isinstance(ev["t"], _NUM) or ev["t"] < 0:
            raise SceneError(f"{source}: timeline[{i}].t: expected a time >= 0, got {ev['t']!r}")
        if ev["topic"] not in TIMELINE_KEYS:
            raise SceneError(f"{source}: timeline[{i}].topic: unknown topic {ev['topic']!r} "
                             f"(wrench, point_force, collider_pose, clear_forces)")
        _check_event(ev, f"{source}: timeline[{i}]", data, warnings)
    return warnings


# Per timeline topic: (required keys, optional keys) besides t and topic.
TIMELINE_KEYS = {
    "wrench": (("frame_id",), ("force", "torque")),
    "point_force": (("point", "force"), ("duration",)),
    "collider_pose": (("name", "position"), ("orientation",)),
    "clear_forces": ((), ()),
}


def _check_event(ev, where, data, warnings):
    """Keys, vectors and names of one timeline event, so a typo fails on load, not mid-run."""
    required, optional = TIMELINE_KEYS[ev["topic"]]
    allowed = {"t", "topic", *required, *optional}
    unknown = sorted(set(ev) - allowed)
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {unknown} for topic {ev['topic']} (allowed: {sorted(allowed)})")
    for key in required:
        if key not in ev:
            raise SceneError(f"{where}.{key}: required for topic {ev['topic']}")
    for key in ("force", "torque", "point", "position"):
        if key in ev:
            _vec3(ev[key], f"{where}.{key}")
    if "orientation" in ev:
        q = ev["orientation"]
        if (not isinstance(q, (list, tuple)) or len(q) != 4
                or not all(isinstance(v, _NUM) and not isinstance(v, bool) for v in q) or not any(q)):
            raise SceneError(f"{where}.orientation: expected a non-zero quaternion [x, y, z, w], got {q!r}")
    if "duration" in ev and (not isinstance(ev["duration"], _NUM) or isinstance(ev["duration"], bool)):
        raise SceneError(f"{where}.duration: expected a number of seconds, got {ev['duration']!r}")
    # An unknown name is a warning, not an error: a timeline may carry an input the node
    # must reject (recordings test exactly that); `mdss run` prints the warnings first.
    if ev["topic"] == "wrench" and ev["frame_id"] not in data["handles"]:
        warnings.append(f"{where}.frame_id: unknown handle {ev['frame_id']!r} "
                        f"(scene handles: {sorted(data['handles'])}); the input will be rejected")
    if ev["topic"] == "collider_pose" and ev["name"] not in data["colliders"]:
        warnings.append(f"{where}.name: unknown collider {ev['name']!r} "
                        f"(scene colliders: {sorted(data['colliders'])}); the input will be rejected")


def _check_body(data, source, base_dir):
    """Mesh source and material, checked before anything is built: a missing mesh file or a
    bad modulus fails at load with the key, not after minutes of meshing."""
    mesh = data["body"]["mesh"]
    where = f"{source}: body.mesh"
    if ("file" in mesh) == ("generator" in mesh):
        raise SceneError(f"{where}: needs exactly one of 'generator' or 'file', got keys {sorted(mesh)}")
    if "file" in mesh:
        if not isinstance(mesh["file"], str):
            raise SceneError(f"{where}.file: expected a path, got {mesh['file']!r}")
        path = base_dir / mesh["file"]
        if not path.is_file():
            raise SceneError(f"{where}.file: mesh file {str(path)!r} not found "
                             f"(relative paths are relative to the scene file's folder)")
    from .fem.materials import make_material
    try:
        make_material(data["body"]["material"])
    except SceneError as err:
        raise SceneError(f"{source}: body.material: {err}") from err


def _check_colliders(data, source, base_dir):
    """Mesh colliders' own keys at load (file found and supported, scale and resolution > 0,
    no unknown key): a wrong path fails with the key before the model is built. Everything
    else about colliders (and a mesh's closedness) is checked by make_collider when the
    Simulator builds them."""
    from .contact.colliders import MESH_KEYS
    from .contact.mesh_sdf import check_spec
    for name, spec in data["colliders"].items():
        if not isinstance(spec, dict) or spec.get("shape") != "mesh":
            continue
        where = f"{source}: colliders.{name}"
        allowed = set(MESH_KEYS) | {"shape", "position", "orientation", "reach", "friction"}
        unknown = sorted(set(spec) - allowed)
        if unknown:
            raise SceneError(f"{where}: unknown key(s) {unknown} for a mesh (allowed: {sorted(allowed)})")
        check_spec(where, spec, base_dir)


# Keys the reduced model reads from its sub-sections (it checks values when it builds).
_MODEL_SUBKEYS = {
    "domains": {"count", "regions", "seed", "auto"},
    "cubature": {"samples", "tolerance", "interface", "interface_samples", "training", "seed"},
    "coupling": {"kind", "stiffness"},
}


def _check_model(model, source):
    """Unknown keys in model.domains / cubature / coupling, and domains given both ways.
    `domains: auto` becomes {auto: true} (reduced/auto_domains.py places them)."""
    if model.get("domains") == "auto":
        model["domains"] = {"auto": True}
    for section, allowed in _MODEL_SUBKEYS.items():
        value = model[section]
        if not isinstance(value, dict):
            raise SceneError(f"{source}: model.{section}: expected a mapping, got {value!r}")
        unknown = sorted(set(value) - allowed)
        if unknown:
            raise SceneError(f"{source}: unknown key(s) {', '.join(f'model.{section}.' + k for k in unknown)} "
                             f"(allowed: {', '.join(sorted(allowed))})")
    given = [k for k in ("count", "regions", "auto") if k in model["domains"]]
    if len(given) > 1:
        raise SceneError(f"{source}: model.domains: give one of count, regions or auto, not {' and '.join(given)}")
    if "auto" in model["domains"]:
        from .reduced.auto_domains import auto_settings     # settings checked on load
        try:
            auto_settings(model["domains"]["auto"])
        except SceneError as err:
            raise SceneError(f"{source}: {err}") from err


def model_config(scene):
    """The `model` section a scene's model is built from: the file's, plus what the scene
    implies. Automatic domains (`model.domains: auto`) without basis.extension or
    basis.layers get basis.extension auto_domains.AUTO_EXTENSION (1.0); the keys set so
    are listed in model["implied"] ({key: why}). A collider's `reach` region (the part of
    the body it can touch) becomes a full-space domain `<collider>_reach` of a reduced
    model (docs/method.md §12): contact there is resolved on every vertex, the rest stays
    reduced. Returns a new dict."""
    model = copy.deepcopy(scene["model"])
    if model["kind"] != "reduced":
        return model
    domains = model.get("domains") or {}
    basis = model.get("basis") or {}
    if "auto" in domains and "extension" not in basis and "layers" not in basis:
        # Automatic domains take bases on regions grown by about one diameter
        # (auto_domains.AUTO_EXTENSION; measured in docs/verification.md, sessions 18-19).
        # Set here, not in domains.build_subspace_domain, so that counts and regions keep
        # 0.5 and the bases' cache key holds the value used; `implied` tells --explain
        # that the scene did not choose it.
        from .reduced.auto_domains import AUTO_EXTENSION
        model["basis"] = dict(basis, extension=AUTO_EXTENSION)
        model.setdefault("implied", {})["basis.extension"] = "the default for model.domains: auto"
    regions = domains.get("regions")
    if isinstance(regions, dict):
        # The first region to select a vertex wins, so their order is an input of the
        # partition; cache keys sort dict keys, so the order is also kept as a list.
        model["domains"]["region_order"] = list(regions)
    reach = {f"{name}_reach": spec["reach"] for name, spec in scene["colliders"].items()
             if isinstance(spec, dict) and spec.get("reach") is not None}
    if reach:
        domains = dict(model.get("domains") or {"count": 1})
        domains["reach"] = reach
        model["domains"] = domains
        model["full_space_domains"] = list(model.get("full_space_domains") or []) + list(reach)
    return model
