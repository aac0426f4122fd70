"""The independent case matrix for ``dragd gap`` and its runner.

    python tests/independent/matrix.py --out /work/scratch/indep/run1 [--cases 'viscous*,none_*'] [--list]
                                       [--reuse] [--timeout 600] [--jobs 2]

Each case (generator.CaseSpec) is written by tests/independent/generator.py — logs made from the equations, not by
dragd or ``sim`` — then the real CLI runs on it:

    dragd gap --measured CASE/log.csv --model CASE/belief.yaml --config CASE/config.yaml [--robot URDF] --json

and the answer is scored against the truth (CASE/truth.json ``expected``):

* **right**: exactly the expected effect names; for each, every *required* joint named (the missing current's 5 Hz
  RMS over sliding samples ≥ 1 × the Hall noise σ) and no joint outside the *allowed* ones (where the effect acts at
  all); an expected name with no required joint may be named or not. "none" cases: nothing named.
* **wrong**: anything else (missed names, extra names, wrong joints — all listed);
* **crash**: the CLI exits non-zero or prints no JSON (the error's last line recorded).

Writes CASE/result.json, OUT/results.json (all cases, the summary, the confusions) and prints a table. Runs
``--jobs`` cases at once (worker processes, default 2), each ``dragd gap`` under ``nice`` with single-threaded BLAS
(a shared 2-core machine). ``dragd bench gap_confusion`` runs the same matrix (dragd/lab/bench/gap_confusion.py).
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import generator as g  # noqa: E402

RATES = (100, 250, 500, 1000)
NOISES = (0.01, 0.02, 0.04)

# ------------------------------------------------------------------------------------------ the matrix


def _vary(k: int) -> dict[str, Any]:
    """Deterministic spread of rate × dq × noise × duration over the cases (k: the case's index in its group)."""
    return {"rate_Hz": RATES[k % 4], "with_dq": (k % 3) != 1, "noise_A": NOISES[(k // 2) % 3],
            "duration_s": (45.0, 60.0, 40.0, 50.0)[(k // 3) % 4]}


def single_effect_cases() -> list[g.CaseSpec]:
    """Each catalogue effect (and the K_t gain error) alone, on each excitation kind, with varied joints/magnitudes.
    constant_speed moves the effect's joint(s) and one neighbour, one at a time."""
    E = g
    per_kind: dict[str, list[tuple[g.Effect, tuple[int, ...]]]] = {
        "viscous_friction": [(E.ViscousFriction(joints=(1,), pos_A_s_per_rad=0.6, neg_A_s_per_rad=0.6), (1, 2)),
                             (E.ViscousFriction(joints=(2, 4), pos_A_s_per_rad=0.4, neg_A_s_per_rad=0.5), (2, 4)),
                             (E.ViscousFriction(joints=(3,), pos_A_s_per_rad=0.35, neg_A_s_per_rad=0.35), (3, 1)),
                             (E.ViscousFriction(joints=(1,), pos_A_s_per_rad=0.5, neg_A_s_per_rad=0.7), (1, 2))],
        "stribeck": [(E.StribeckHump(joints=(1,), hump_A=0.35, velocity_rad_s=0.1, exponent=1.0), (1, 2)),
                     (E.StribeckHump(joints=(2,), hump_A=0.25, velocity_rad_s=0.08, exponent=1.5), (2, 1)),
                     (E.StribeckHump(joints=(3,), hump_A=0.2, velocity_rad_s=0.12, exponent=1.0), (3, 1)),
                     (E.StribeckHump(joints=(1, 2), hump_A=0.3, velocity_rad_s=0.1, exponent=2.0), (1, 2))],
        "position_periodic": [(E.PositionRipple(joints=(2,), amplitude_Nm=0.5, cycles_per_rev=24.0), (2, 1)),
                              (E.PositionRipple(joints=(4,), amplitude_Nm=0.15, cycles_per_rev=36.0), (4, 1)),
                              (E.PositionRipple(joints=(1,), amplitude_Nm=0.8, cycles_per_rev=12.0), (1, 2)),
                              (E.PositionRipple(joints=(2,), amplitude_Nm=0.6, cycles_per_rev=18.0, phase_rad=2.0),
                               (2, 1))],
        "load_dependent_friction": [(E.LoadFriction(joints=(1,), coefficient=0.04), (1, 2)),
                                    (E.LoadFriction(joints=(2,), coefficient=0.05), (2, 1)),
                                    (E.LoadFriction(joints=(1, 2), coefficient=0.03), (1, 2)),
                                    (E.LoadFriction(joints=(1,), coefficient=0.025), (1, 2))],
        "inertia": [(E.MissingDynamics(), (1, 2))] * 4,
        "temperature_drift": [(E.TemperatureDrift(joints=(1,)), (1, 2)),
                              (E.TemperatureDrift(joints=(1, 2), delta_T_K=30.0, time_constant_s=15.0), (1, 2)),
                              (E.TemperatureDrift(joints=(3,), delta_T_K=25.0, time_constant_s=25.0), (3, 1)),
                              (E.TemperatureDrift(joints=(1,), delta_T_K=20.0, time_constant_s=40.0), (1, 2))],
        "backlash": [(E.Backlash(joints=(0,), play_rad=0.015), (0,)), (E.Backlash(joints=(0,), play_rad=0.012), (0,)),
                     (E.Backlash(joints=(3,), play_rad=0.01), (3,)), (E.Backlash(joints=(0,), play_rad=0.015), (0,))],
        "back_emf": [(E.BackEmf(joints=(1,), knee_rad_s=0.3), (1, 2)),
                     (E.BackEmf(joints=(3,), ke_V_s_per_rad=0.005, knee_rad_s=0.35), (3, 1)),
                     (E.BackEmf(joints=(2,), knee_rad_s=0.15, ke_V_s_per_rad=0.006), (2, 1)),
                     (E.BackEmf(joints=(1,), knee_rad_s=0.25), (1, 2))],
        "payload_mass": [(E.Payload(mass_kg=1.5), (1, 2)), (E.Payload(mass_kg=2.5, com_flange_m=(0.03, 0.0, 0.08)),
                                                            (1, 2)),
                         (E.Payload(mass_kg=1.0, com_flange_m=(0.0, 0.02, 0.05)), (1, 2)),
                         (E.Payload(mass_kg=2.0), (1, 2))],
        "current_offset": [(E.CurrentOffset(joints=(3,), offset_A=0.08), (3, 1)),
                           (E.CurrentOffset(joints=(1,), offset_A=-0.06), (1, 2)),
                           (E.CurrentOffset(joints=(5,), offset_A=0.05), (5, 1)),
                           (E.CurrentOffset(joints=(2,), offset_A=0.1), (2, 1))],
        "torque_constant": [(E.TorqueConstantError(joints=(1,), relative=-0.2), (1, 2)),
                            (E.TorqueConstantError(joints=(0,), relative=0.45), (0, 1)),
                            (E.TorqueConstantError(joints=(4,), relative=0.3), (4, 1)),
                            (E.TorqueConstantError(joints=(2,), relative=0.15), (2, 1))],
    }
    kinds = ("trapezoid", "fourier", "ptp", "constant_speed")
    out = []
    k = 0
    for name, variants in per_kind.items():
        for v, (eff, moving) in enumerate(variants):
            kind = kinds[v]
            out.append(g.CaseSpec(f"{name}__{kind}", excitation=kind, effects=(eff,), seed=100 + k,
                                  moving_joints=moving, description=f"{name} alone", **_vary(k)))
            k += 1
    return out


def pair_cases() -> list[g.CaseSpec]:
    """Two hidden effects at once."""
    E = g
    pairs = [
        ("ripple3+offset4", "trapezoid", (E.PositionRipple(joints=(2,)), E.CurrentOffset(joints=(3,))), None),
        ("viscous2+backemf4", "fourier", (E.ViscousFriction(joints=(1,)), E.BackEmf(joints=(3,), ke_V_s_per_rad=0.005,
                                                                                   knee_rad_s=0.35)), None),
        ("payload+loadfric2", "ptp", (E.Payload(mass_kg=1.5), E.LoadFriction(joints=(1,))), None),
        ("drift2+ripple5", "trapezoid", (E.TemperatureDrift(joints=(1,)), E.PositionRipple(joints=(4,),
                                                                                          amplitude_Nm=0.15,
                                                                                          cycles_per_rev=36.0)), None),
        ("stribeck3+offset2", "constant_speed", (E.StribeckHump(joints=(2,)), E.CurrentOffset(joints=(1,))), (2, 1)),
        ("inertia+viscous2", "fourier", (E.MissingDynamics(), E.ViscousFriction(joints=(1,))), None),
        ("kt2+payload", "ptp", (E.TorqueConstantError(joints=(1,), relative=-0.15), E.Payload(mass_kg=1.5)), None),
        ("backlash1+payload", "trapezoid", (E.Backlash(joints=(0,), play_rad=0.015), E.Payload(mass_kg=1.5)), None),
        ("backlash1+offset1", "fourier",
         (E.Backlash(joints=(0,), play_rad=0.015), E.CurrentOffset(joints=(0,), offset_A=0.08)), None),
    ]
    return [g.CaseSpec(f"pair__{nm}", excitation=kind, effects=effs, seed=300 + k, moving_joints=mv,
                       description="two effects at once", **_vary(k + 1))
            for k, (nm, kind, effs, mv) in enumerate(pairs)]


def none_cases() -> list[g.CaseSpec]:
    """Nothing hidden, the belief equals the truth: nothing may be named."""
    out = []
    for k, kind in enumerate(("trapezoid", "fourier", "ptp", "constant_speed") * 2):
        out.append(g.CaseSpec(f"none__{kind}_{k // 4}", excitation=kind, seed=500 + k, moving_joints=(1, 2),
                              description="clean: belief = truth", **_vary(k + 2)))
    return out


def belief_error_cases() -> list[g.CaseSpec]:
    """The truth is the robot's; the user's belief is off (K_t, friction levels, viscous slopes by up to ±40 %)."""
    E = g
    all6 = (0, 1, 2, 3, 4, 5)
    cases = [
        ("coulomb2_+25pct", "trapezoid", (E.CoulombBeliefError(joints=(1,), relative=0.25),)),
        ("coulomb_all_-30pct", "fourier", (E.CoulombBeliefError(joints=all6, relative=-0.3),)),
        ("viscous_all_-40pct", "ptp", (E.ViscousBeliefError(joints=all6, relative=-0.4),)),
        ("viscous3_+40pct", "trapezoid", (E.ViscousBeliefError(joints=(2,), relative=0.4),)),
        ("kt_mixed", "fourier", (E.TorqueConstantError(joints=(0, 2), relative=0.3),
                                 E.TorqueConstantError(joints=(1, 4), relative=-0.25))),
        ("all_off", "ptp", (E.TorqueConstantError(joints=(1, 3), relative=0.2),
                            E.ViscousBeliefError(joints=(0, 2, 5), relative=-0.35),
                            E.CoulombBeliefError(joints=(4,), relative=0.3))),
    ]
    return [g.CaseSpec(f"belief__{nm}", excitation=kind, effects=effs, seed=700 + k, description="belief error",
                       **_vary(k + 3)) for k, (nm, kind, effs) in enumerate(cases)]


def ur5_cases() -> list[g.CaseSpec]:
    """Another URDF: example-robot-data's UR5 (joints renamed joint1..6; one case with its original names)."""
    E = g
    cases = [
        ("none", "trapezoid", ()),
        ("viscous2", "fourier", (E.ViscousFriction(joints=(1,)),)),
        ("payload", "ptp", (E.Payload(mass_kg=2.0),)),
        ("ripple3", "trapezoid", (E.PositionRipple(joints=(2,), amplitude_Nm=0.6),)),
        ("kt2", "fourier", (E.TorqueConstantError(joints=(1,), relative=0.2),)),
        ("offset4", "ptp", (E.CurrentOffset(joints=(3,)),)),
    ]
    out = [g.CaseSpec(f"ur5__{nm}", robot="ur5", excitation=kind, effects=effs, seed=900 + k,
                      description="UR5 (example-robot-data)", **_vary(k)) for k, (nm, kind, effs) in enumerate(cases)]
    out.append(g.CaseSpec("ur5__original_joint_names", robot="ur5_original_names", excitation="trapezoid", seed=950,
                          description="UR5 URDF as shipped (joints shoulder_pan_joint, ...)", **_vary(1)))
    return out


def ambiguity_cases() -> list[g.CaseSpec]:
    """Data that cannot tell two effects apart: joint 1 (no gravity) moved alone at constant speeds — its whole torque
    is M₁₁·q̈₁ (M₁₁ constant while the others hold), so a K_t error on it and a rotor-inertia error are the same column.
    The right answer names one and reports the other as ambiguous."""
    E = g
    return [g.CaseSpec("ambiguous__kt1_or_inertia_single_joint", excitation="constant_speed", seed=1100,
                       effects=(E.TorqueConstantError(joints=(0,), relative=0.45),), moving_joints=(0,),
                       rate_Hz=500, with_dq=False, noise_A=0.02, duration_s=40.0,
                       description="K_t 45 % off on joint 1, moved alone: indistinguishable from its inertia")]


def all_cases() -> list[g.CaseSpec]:
    return (single_effect_cases() + pair_cases() + none_cases() + belief_error_cases() + ur5_cases()
            + ambiguity_cases())


# ------------------------------------------------------------------------------------------ running and scoring


def dragd_command() -> list[str]:
    exe = Path(sys.executable).parent / "dragd"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "dragd"]


def run_gap(case_dir: Path, info: dict[str, Any], timeout_s: float, nice: bool = False) -> dict[str, Any]:
    """``dragd gap`` on one case (``nice``: at nice 10, for the whole matrix in the background; a test runs it at the
    test's own priority: niced beside a busy test suite it waited for CPU 20 times as long as it computed)."""
    cmd = dragd_command() + ["gap", "--measured", str(case_dir / "log.csv"), "--model", str(case_dir / "belief.yaml"),
                             "--config", str(case_dir / "config.yaml")]
    if info.get("pass_robot_flag"):
        cmd += ["--robot", info["urdf"]]
    cmd += ["--json"]
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="Agg")
    t0 = time.time()
    try:
        proc = subprocess.run((["nice", "-n", "10"] if nice else []) + cmd, capture_output=True, text=True,
                              timeout=timeout_s, env=env)
    except subprocess.TimeoutExpired:
        return {"cmd": cmd, "returncode": None, "error": f"timeout after {timeout_s:.0f} s", "elapsed_s": timeout_s}
    res: dict[str, Any] = {"cmd": cmd, "returncode": proc.returncode, "elapsed_s": round(time.time() - t0, 1),
                           "stderr_tail": proc.stderr.strip().splitlines()[-12:]}
    if proc.returncode != 0:
        lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
        res["error"] = lines[-1] if lines else f"exit {proc.returncode}"
        res["traceback"] = "Traceback" in proc.stderr
        return res
    try:
        res["json"] = json.loads(proc.stdout.strip().splitlines()[-1])
    except (json.JSONDecodeError, IndexError) as exc:
        res["error"] = f"no JSON on stdout: {exc}"
    return res


def score(expected: dict[str, Any], answer: dict[str, Any] | None) -> dict[str, Any]:
    """right / wrong (with the reasons) for a gap JSON answer against the truth's expected effects.

    An effect reported as ``ambiguous_with`` a named one (the data explain those joints equally well by either) counts
    as named on those joints when it is expected, and is not counted as an extra name when it is not: the answer "A or
    B" is right when the truth is one of them. Such cases are marked ``ambiguous`` (fraction reported separately)."""
    named: dict[str, set[str]] = {}
    alt: dict[str, set[str]] = {}
    for e in (answer or {}).get("effects", []):
        named.setdefault(e["effect"], set()).update(e["joints"])
        for a in e.get("ambiguous_with", []):
            alt.setdefault(a["effect"], set()).update(a["joints"])
    need = {k: v for k, v in expected.items() if v["required"]}
    reasons = []
    used_alt: dict[str, list[str]] = {}
    for nm, v in need.items():
        got = named.get(nm, set()) | alt.get(nm, set())
        if not got:
            reasons.append(f"missed {nm} ({','.join(v['required'])})")
            continue
        miss = sorted(set(v["required"]) - got)
        if miss:
            reasons.append(f"{nm}: joints {','.join(miss)} not named")
        via = sorted((set(v["required"]) & alt.get(nm, set())) - named.get(nm, set()))
        if via:
            used_alt[nm] = via
    for nm, js in named.items():
        if nm not in expected:
            # a name given only as one of equally good explanations of an expected effect is not an extra name
            if used_alt and all(any(j in js_alt for js_alt in used_alt.values()) for j in js):
                continue
            reasons.append(f"extra {nm} ({','.join(sorted(js))})")
            continue
        bad = sorted(js - set(expected[nm]["allowed"]))
        if bad:
            reasons.append(f"{nm}: named on {','.join(bad)} where it does not act")
    return {"status": "right" if not reasons else "wrong", "reasons": reasons,
            "named": {k: sorted(v) for k, v in named.items()},
            "ambiguous": {k: sorted(v) for k, v in alt.items()}, "right_via_ambiguity": used_alt,
            "expected": {k: v["required"] for k, v in need.items()},
            "optional": sorted(k for k, v in expected.items() if not v["required"])}


def confusions(results: list[dict[str, Any]]) -> Counter:
    """Over the wrong cases: (expected → what was named instead). A missed name pairs with each extra name (or '—');
    extra names beside right ones pair as '+ name'; right names on wrong joints as 'joints'."""
    c: Counter = Counter()
    for r in results:
        if r["status"] != "wrong":
            continue
        sc = r["score"]
        exp, got = set(sc["expected"]), set(sc["named"])
        missing = sorted(exp - got)
        extra = sorted(got - exp - set(sc["optional"]))
        if missing:
            for m in missing:
                for x in extra or ["—"]:
                    c[(m, x)] += 1
        elif extra:
            for x in extra:
                c[("+".join(sorted(exp)) or "none", ("+ " if exp else "") + x)] += 1
        else:
            c[("+".join(sorted(exp)), "joints: " + "; ".join(sc["reasons"]))] += 1
    return c


def run_case(spec: g.CaseSpec, out: Path, reuse: bool = False, timeout_s: float = 600.0,
             generate_only: bool = False, nice: bool = False) -> dict[str, Any]:
    """Generate one case under ``out/CASE_ID``, run ``dragd gap`` on it and score the answer (CASE/result.json)."""
    cdir = out / spec.case_id
    rfile = cdir / "result.json"
    if reuse and rfile.is_file():
        return json.loads(rfile.read_text())
    if cdir.exists():
        shutil.rmtree(cdir)
    t0 = time.time()
    try:
        info = g.generate(spec, cdir)
    except Exception as exc:  # a generator failure is ours, not dragd's: report and go on
        return {"case_id": spec.case_id, "status": "generator_error", "error": repr(exc), "spec": g.spec_to_json(spec)}
    gen_s = time.time() - t0
    if generate_only:
        return {"case_id": spec.case_id, "status": "generated", "expected_detail": info["expected"],
                "generate_s": round(gen_s, 1)}
    run = run_gap(cdir, info, timeout_s, nice)
    sc = score(info["expected"], run.get("json"))
    status = sc["status"] if "json" in run else "crash"
    r = {"case_id": spec.case_id, "status": status, "spec": g.spec_to_json(spec), "score": sc,
         "expected_detail": info["expected"], "run": {k: v for k, v in run.items() if k != "cmd"},
         "command": " ".join(run["cmd"]), "generate_s": round(gen_s, 1)}
    if "json" in run:
        j = run["json"]
        r["rmse_mA"] = {"baseline": _ma(j["baseline"]["rmse_A"]), "final": _ma(j["final"]["rmse_A"])}
        r["effects_json"] = j["effects"]
    rfile.write_text(json.dumps(r, indent=1))
    return r


def _line(n: int, total: int, r: dict[str, Any]) -> str:
    if r["status"] in ("generator_error",):
        return f"[{n}/{total}] {r['case_id']}: GENERATOR ERROR {r['error']}"
    if r["status"] == "generated":
        return (f"[{n}/{total}] {r['case_id']:38s} gen {r['generate_s']:4.1f}s expected "
                f"{ {k: v['required'] for k, v in r['expected_detail'].items()} }")
    sc, run = r["score"], r["run"]
    tail = run.get("error", "") if r["status"] == "crash" else "; ".join(sc["reasons"])
    return (f"[{n}/{total}] {r['case_id']:38s} {r['status']:6s} gen {r['generate_s']:4.1f}s gap "
            f"{run.get('elapsed_s', 0):5.1f}s named {_fmt_named(sc['named'])}  {tail}")


def run_matrix(out: Path, cases: list[g.CaseSpec] | None = None, jobs: int = 2, reuse: bool = False,
               timeout_s: float = 600.0, generate_only: bool = False, echo: Any = None) -> list[dict[str, Any]]:
    """Every case (``all_cases()`` by default), ``jobs`` at a time in worker processes (each runs its own ``dragd gap``
    process, single-threaded BLAS, under ``nice``); results in the cases' order. ``echo``: called with a progress line
    per finished case."""
    from concurrent.futures import ProcessPoolExecutor

    cases = all_cases() if cases is None else cases
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, Any]] = {}
    if jobs <= 1:
        for k, spec in enumerate(cases, 1):
            results[spec.case_id] = r = run_case(spec, out, reuse, timeout_s, generate_only, nice=True)
            if echo:
                echo(_line(k, len(cases), r))
    else:
        with ProcessPoolExecutor(max_workers=jobs) as ex:
            futs = {ex.submit(run_case, spec, out, reuse, timeout_s, generate_only, True): spec for spec in cases}
            from concurrent.futures import as_completed
            for k, f in enumerate(as_completed(futs), 1):
                results[futs[f].case_id] = r = f.result()
                if echo:
                    echo(_line(k, len(cases), r))
    return [results[c.case_id] for c in cases]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="output directory (one folder per case, results.json); required unless --list")
    ap.add_argument("--cases", help="comma-separated case ids or shell patterns (default: all)")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--reuse", action="store_true", help="keep a case's existing result.json (resume a run)")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per dragd gap run")
    ap.add_argument("--jobs", type=int, default=2, help="cases run at once (worker processes; default 2)")
    ap.add_argument("--generate-only", action="store_true", help="write the cases' files and expectations, no dragd")
    args = ap.parse_args(argv)
    cases = select_cases(args.cases)
    if args.list:
        for c in cases:
            print(f"{c.case_id:40s} {c.robot:10s} {c.excitation:15s} {c.rate_Hz:5d} Hz dq={int(c.with_dq)} "
                  f"σ={c.noise_A * 1e3:.0f} mA {c.duration_s:.0f} s  {', '.join(e.name for e in c.effects) or 'none'}")
        print(f"{len(cases)} cases")
        return 0
    if not args.out:
        ap.error("--out: required (the directory for the cases and results.json)")
    out = Path(args.out)
    results = run_matrix(out, cases, args.jobs, args.reuse, args.timeout, args.generate_only,
                         echo=lambda ln: print(ln, flush=True))
    if args.generate_only:
        return 0
    summary = summarise(results)
    (out / "results.json").write_text(json.dumps({"summary": summary, "cases": results}, indent=1))
    print_summary(results, summary)
    return 0


def select_cases(patterns: str | None) -> list[g.CaseSpec]:
    """The matrix's cases whose ids match any of the comma-separated shell patterns (all when None)."""
    cases = all_cases()
    if patterns:
        pats = [p.strip() for p in patterns.split(",") if p.strip()]
        cases = [c for c in cases if any(fnmatch.fnmatch(c.case_id, p) for p in pats)]
    return cases


def _ma(x: float | None) -> float | None:
    return None if x is None else round(x * 1e3, 2)


def _fmt_named(named: dict[str, list[str]]) -> str:
    if not named:
        return "—"
    return " ".join(f"{k}({','.join(j.replace('joint', '') for j in v)})" for k, v in named.items())


def _group(case_id: str) -> str:
    return case_id.split("__")[0]


def summarise(results: list[dict[str, Any]]) -> dict[str, Any]:
    by: dict[str, Counter] = {}
    for r in results:
        by.setdefault(_group(r["case_id"]), Counter())[r["status"]] += 1
    tot = Counter(r["status"] for r in results)
    in_cat = [r for r in results if not set(r.get("score", {}).get("expected", {})) & set(g.NAMES_NOT_IN_CATALOGUE)]
    conf = confusions(results)
    return {
        "cases": len(results), "counts": dict(tot),
        "fraction_right": round(tot["right"] / max(len(results), 1), 3),
        "right_ambiguous": sum(r["status"] == "right" and bool(r["score"].get("right_via_ambiguity"))
                               for r in results),
        "fraction_right_catalogue_only": round(sum(r["status"] == "right" for r in in_cat) / max(len(in_cat), 1), 3),
        "catalogue_only_cases": len(in_cat),
        "by_group": {k: dict(v) for k, v in by.items()},
        "crashes": [{"case_id": r["case_id"], "error": r.get("run", {}).get("error", r.get("error"))}
                    for r in results if r["status"] in ("crash", "generator_error")],
        "confusions": [{"expected": a, "named_instead": b, "cases": n} for (a, b), n in conf.most_common()],
    }


def print_summary(results: list[dict[str, Any]], s: dict[str, Any]) -> None:
    print()
    print(f"{'case':40s} {'status':7s} {'expected':34s} named")
    for r in results:
        sc = r.get("score", {})
        exp = _fmt_named(sc.get("expected", {})) if sc else "?"
        print(f"{r['case_id']:40s} {r['status']:7s} {exp:34s} {_fmt_named(sc.get('named', {})) if sc else ''}")
    print()
    print("by group: " + "; ".join(f"{k}: {dict(v)}" for k, v in s["by_group"].items()))
    print(f"right {s['counts'].get('right', 0)}/{s['cases']} = {s['fraction_right']:.0%} "
          f"(catalogue-only expectations: {s['fraction_right_catalogue_only']:.0%} of {s['catalogue_only_cases']})")
    for c in s["crashes"]:
        print(f"crash {c['case_id']}: {c['error']}")
    print("confusions (expected → named instead, cases):")
    for c in s["confusions"][:25]:
        print(f"  {c['expected']:32s} → {c['named_instead']}  ×{c['cases']}")


if __name__ == "__main__":
    sys.exit(main())
