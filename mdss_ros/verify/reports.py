"""The `mdss verify` reports: which exist, and running one or all of them into a folder
(JSON, PNG plots and a summary table each). The studies themselves are one module each
(verify/*_study.py); their shared helpers are in verify/reduced_reports.py."""
import os
import time
from pathlib import Path

from ..errors import ReportError
from .reduced_reports import Progress, environment, format_table, write_json

BUILT = ("energy", "coupling", "reduced", "cantilever", "modes", "cubature", "hertz", "meshless", "contact", "friction")
NOT_BUILT = ()


def _study(name):
    if name == "energy":
        from .energy_study import energy_report
        return energy_report
    if name == "coupling":
        from .coupling_study import coupling_report
        return coupling_report
    if name == "reduced":
        from .accuracy_study import accuracy_report
        return accuracy_report
    if name == "cantilever":
        from .cantilever_study import cantilever_report
        return cantilever_report
    if name == "cubature":
        from .cubature_study import cubature_report
        return cubature_report
    if name == "modes":
        from .modes_study import modes_report
        return modes_report
    if name == "hertz":
        from .hertz_study import hertz_report
        return hertz_report
    if name == "meshless":
        from .meshless_study import meshless_report
        return meshless_report
    if name == "contact":
        from .contact_study import contact_report
        return contact_report
    if name == "friction":
        from .friction_study import friction_report
        return friction_report
    raise KeyError(name)


def check_name(name):
    """Raise ReportError with a clear message for a report that is not available."""
    if name in BUILT or name == "all":
        return
    if name in NOT_BUILT:
        raise ReportError(f"verify report {name!r} is not built yet in this version "
                          f"(built: {', '.join(BUILT)}, all)")
    planned = f"; planned: {', '.join(NOT_BUILT)}" if NOT_BUILT else ""
    raise ReportError(f"unknown verify report {name!r} (available: {', '.join(BUILT)}, all{planned})")


def run_report(name, out, quick=False, overrides=None):
    """Run one report into directory `out`; returns its result dict (also in out/NAME.json)."""
    check_name(name)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log = Progress(name)
    env_start = environment()
    log(f"start ({'quick' if quick else 'default'} run) -> {out}; load average {env_start['load_average']} "
        f"on {env_start['cpus']} CPUs")
    result = _study(name)(out, quick=quick, overrides=overrides, log=log)
    result["wall_s"] = log.elapsed()
    result["report"] = name
    result["environment"] = dict(environment(), load_average_start=env_start["load_average"])
    result["plots"] = [str(Path(p).name) for p in result.get("plots", [])]
    path = write_json(out, name, result)
    print(f"\n== mdss verify {name}: summary ==\n{result['table']}", flush=True)
    for note in result.get("notes", []):
        print(f"  note: {note}")
    load = lambda env: "?" if not env["load_average"] else f"{env['load_average'][0]:.2f}"    # noqa: E731
    print(f"wrote {path} and {', '.join(result['plots'])} ({result['wall_s']:.1f} s wall; 1-min load average "
          f"{load(env_start)} at start, {load(result['environment'])} at end, {os.cpu_count()} CPUs)\n", flush=True)
    return result


def run_reports(name, out, quick=False, overrides=None):
    """`mdss verify NAME`: one report, or all built ones for NAME == "all". Returns 0."""
    check_name(name)
    if name != "all":
        run_report(name, out, quick, overrides)
        return 0
    if overrides:
        raise ReportError("--set applies to one report; run the reports one by one to override settings")
    t0 = time.perf_counter()
    walls = {}
    for n in BUILT:
        walls[n] = run_report(n, out, quick)["wall_s"]
    print("== mdss verify all ==\n" + format_table(["report", "wall (s)"], [[n, w] for n, w in walls.items()])
          + f"\ntotal {time.perf_counter() - t0:.1f} s", flush=True)
    return 0
