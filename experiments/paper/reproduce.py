"""`python -m experiments reproduce --quick|--full [--out DIR]`: the paper's evaluation in one command, one report.

Runs Fig. 4a (surrogate returns relative to DP optimal, RM-ANOVA), Table 1 (online wall-clock per unseen episode)
and Fig. 4b (the same policies in MJX, or C MuJoCo with --backend c) in sequence, then writes DIR/REPORT.md with the
figures, tables, and, claim by claim, whether our numbers agree with the paper's. Presets:

  quick  (CPU, ~15-25 min): the shipped (or your trained) PPO policy; Fig. 4a on 9 of the 27 evaluation episodes
         stepped on their DP tables; Table 1 on one episode; Fig. 4b on 2 episodes (one per evaluation set).
  full   (GPU): trains the PPO policy first if there is none (`train --preset full --seeds 1`); Fig. 4a on all 27
         episodes stepped in the surrogate itself (checked against the tables); Table 1 also batched over the 27;
         Fig. 4b on all 27.

Every stage writes its own results (results/fig4a, table1, fig4b), and Fig. 4b keeps each finished policy, so a
rerun after an interruption redoes little.
"""
from __future__ import annotations

import argparse
import datetime
import pathlib
import shutil
import time

import jax
import numpy as np

from experiments import cli, common
from experiments.common import Run
from gsp_jax.planning import evaluation
from gsp_jax.core import files, stats
from gsp_jax.planners import registry as planners

PRESETS = {
    "quick": dict(fig4a_episodes=9, backend="table", batch=0, repeats=1, fig4b_episodes=2, train=False),
    "full": dict(fig4a_episodes=None, backend="surrogate", batch=27, repeats=3, fig4b_episodes=None, train=True),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--quick", dest="preset", action="store_const", const="quick", help="CPU preset (the default)")
    g.add_argument("--full", dest="preset", action="store_const", const="full", help="GPU preset")
    p.add_argument("--out", default="results/report", help="where REPORT.md and its figures go")
    p.add_argument("--policy-dir", default=None,
                   help="PPO policy (default: results/train/dp/seed0, else the shipped one)")
    p.add_argument("--train", action="store_true",
                   help="train the PPO policy first (full preset, seed 0) even if a trained or shipped one exists")
    p.add_argument("--fig4a-backend", default=None, choices=["table", "surrogate"],
                   help="override the preset's Fig. 4a backend (table: the episodes' DP tables, exact on the discrete "
                        "states the policies visit, e.g. the full preset's 27 episodes on a CPU)")
    p.add_argument("--backend", default="mjx", choices=["mjx", "c"],
                   help="Fig. 4b's physics engine: mjx (one XLA batch) or c (C MuJoCo, the same controller)")
    p.add_argument("--skip", nargs="*", default=[], choices=["fig4a", "table1", "fig4b"], help="stages to leave out")
    p.add_argument("--report-only", action="store_true",
                   help="rebuild REPORT.md from the saved results (e.g. copied back from a GPU run) without rerunning")


def _trains(args: argparse.Namespace, p: dict) -> bool:
    """Whether the run trains the PPO policy first (--train, or the preset trains and no policy is there)."""
    have_policy = (common.RESULTS / "train" / evaluation.TRAINED_POLICY).exists() or evaluation.SHIPPED_POLICY.exists()
    return args.policy_dir is None and (args.train or (p["train"] and not have_policy))


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up (its
    stages' commands then hold them already)."""
    if args.report_only:
        return []
    train = [("train",)] if _trains(args, PRESETS[args.preset or "quick"]) else []
    return train + [(stage,) for stage in ("fig4a", "table1", "fig4b") if stage not in args.skip]


def main(args: argparse.Namespace, run: Run) -> None:
    preset = args.preset or "quick"
    p = PRESETS[preset]
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.report_only:
        return rebuild(out)
    t_start = time.perf_counter()
    device = jax.local_devices()[0]
    print(f"reproduce --{preset} on {device.device_kind} ({device.platform}); "
          f"report -> {out / 'REPORT.md'}", flush=True)
    if _trains(args, p):
        print("[0/3] training the PPO policy (DP pretraining, full preset, seed 0)", flush=True)
        cli.run_command(["train", "--pretrain", "dp", "--seeds", "1", "--preset", "full"], run)
    command = (f"python -m experiments reproduce --{preset}"
               + (f" --policy-dir {args.policy_dir}" if args.policy_dir else ""))
    command += f" --backend {args.backend}" if getattr(args, "backend", "mjx") != "mjx" else ""
    command += f" --skip {' '.join(args.skip)}" if args.skip else ""
    sections = dict(preset=preset, device=f"{device.device_kind} ({device.platform})", command=command,
                    date=datetime.datetime.now().isoformat(timespec="minutes"))
    saved = out / "report.json"
    if args.skip and saved.exists():  # a partial run adds to the stages already reported in `out`
        previous = files.reuse_json(saved, lambda r: isinstance(r, dict)) or {}
        if previous.get("preset") == preset:
            kept = [n for key, n in (("fig4a", "Fig. 4a"), ("table1", "Table 1"), ("fig4b", "Fig. 4b"))
                    if key in args.skip and key in previous]
            if kept:
                sections["provenance"] = (f"{' and '.join(kept)} from `{previous.get('command')}` on "
                                          f"{previous.get('device')}, {previous.get('date')}.")
            sections = previous | sections

    policy = ["--policy-dir", args.policy_dir] if args.policy_dir else []
    only = lambda n: [] if n is None else ["--episodes", str(n)]  # noqa: E731
    if "fig4a" not in args.skip:
        backend_4a = getattr(args, "fig4a_backend", None) or p["backend"]
        print(f"[1/3] Fig. 4a ({backend_4a} backend)", flush=True)
        cli.run_command(["fig4a", "--backend", backend_4a, *only(p["fig4a_episodes"]), *policy], run)
        sections["fig4a"] = files.read_json(run.results_dir("fig4a") / "returns.json")
        shutil.copy(run.results_dir("fig4a") / "fig4a.png", out / "fig4a.png")
    if "table1" not in args.skip:
        print("[2/3] Table 1", flush=True)
        cli.run_command(["table1", "--batch", str(p["batch"]), "--repeats", str(p["repeats"]), *policy], run)
        sections["table1"] = files.read_json(run.results_dir("table1") / f"{device.platform}.json")
    if "fig4b" not in args.skip:
        backend = getattr(args, "backend", "mjx")
        print(f"[3/3] Fig. 4b ({backend})", flush=True)
        # beyond the paper, in C MuJoCo: L1 verified in physics (its defaults, `evaluation.L1_PHYSICS`)
        names = planners.names("paper") + (planners.names("verified") if backend == "c" else ())
        cli.run_command(["fig4b", "--backend", backend, "--policies", *names, *only(p["fig4b_episodes"]), *policy],
                        run)
        sections["fig4b"] = {n: files.read_json(run.results_dir("fig4b") / f"{n}.json") for n in names}
        shutil.copy(run.results_dir("fig4b") / "fig4b.png", out / "fig4b.png")
    files.write_json(out / "report.json", sections, default=str)
    files.write_text(out / "REPORT.md", report(sections))
    print(f"wrote {out / 'REPORT.md'} ({(time.perf_counter() - t_start) / 60:.1f} min)")


def rebuild(out: pathlib.Path) -> None:
    """REPORT.md from out/report.json, with the statistics recomputed (statsmodels may be missing where it ran)."""
    if not (out / "report.json").exists():
        raise SystemExit(f"--report-only: no {out / 'report.json'} (run the stages first, or --out docs/report for the "
                         "committed GPU run)")
    sections = files.read_json(out / "report.json")
    if "fig4a" in sections:
        f = sections["fig4a"]
        f |= stats.relative_returns(f["returns"], "dp-opt", [n for n in f["returns"] if n != "dp-opt"], f["r_min"])
        common.fig4a_png(f["relative"], len(f["episodes"]), out / "fig4a.png")
    if "fig4b" in sections:
        common.fig4b_png(sections["fig4b"], len(next(iter(sections["fig4b"].values()))["episodes"]), out / "fig4b.png")
    files.write_json(out / "report.json", sections, default=str)
    files.write_text(out / "REPORT.md", report(sections))
    print(f"wrote {out / 'REPORT.md'}")


# ----------------------------------------------------------------------------------------------------- report
def _claims(sections: dict) -> list[tuple[str, str, str]]:
    """(paper's claim, ours, agrees?) from the measured numbers."""
    rows = []
    if sections.get("fig4a", {}).get("anova"):
        f = sections["fig4a"]
        tests = {kind: {(c["a"], c["b"]): c for c in f[kind]["posthoc"]} for kind in ("anova", "rank") if f.get(kind)}

        def compare(kind, a, b):  # (a - b, Holm p) from the post-hoc tests of `kind`
            post = tests.get(kind, {})
            if (a, b) in post:
                return post[(a, b)]["diff"], post[(a, b)]["p_holm"]
            if (b, a) in post:
                return -post[(b, a)]["diff"], post[(b, a)]["p_holm"]
            return float("nan"), float("nan")

        def claim(a, b, text):
            diff, p = compare("anova", a, b)
            med, p_rank = compare("rank", a, b)
            ours = (f"mean {a} - {b} = {diff:+.3f}, paired t Holm p = {p:.3g}; "
                    f"median {med:+.3f}, Wilcoxon Holm p = {p_rank:.3g}")
            if diff > 0 and p < 0.05:
                return text, ours, "yes"
            return text, ours, "rank test only" if med > 0 and p_rank < 0.05 else "no"

        for a in ("rl", "L1", "L2"):
            rows.append(claim(a, "dp-base", f"{a} significantly outperforms DP baseline (surrogate)"))
        for a in ("L1", "L2"):
            rows.append(claim(a, "rl", f"{a} significantly outperforms RL (P < 0.05, surrogate)"))
        rel = f["relative"]
        gain1, gain2 = rel["L1"]["mean"] - rel["rl"]["mean"], rel["L2"]["mean"] - rel["L1"]["mean"]
        rows.append(("most of the lookahead gain comes from L1 (diminishing returns)",
                     f"RL -> L1 {gain1:+.3f}, L1 -> L2 {gain2:+.3f}", "yes" if gain1 > 0 and gain2 <= gain1 else "no"))
    if "table1" in sections:
        t = sections["table1"]["policies"]
        ok = all(t[n]["warm_s"] < t["dp-opt"]["warm_s"] for n in ("dp-base", "rl", "L1", "L2"))
        rows.append(("DP optimal is by far the most expensive online (151.79 s vs <= 4.30 s)",
                     ", ".join(f"{n} {r['warm_s']:.3g} s" for n, r in t.items()), "yes" if ok else "no"))
    if "fig4b" in sections:
        b = {n: r for n, r in sections["fig4b"].items() if n in planners.names("paper")}  # the paper's policies
        errors = {n: r["mean_deg"] for n, r in b.items()}
        tied = max(errors.values()) - min(errors.values()) < 1e-6
        listing = ", ".join(f"{n} {e:.1f}" for n, e in errors.items())
        best = min(errors, key=errors.get)
        first = errors["dp-opt"] <= min(errors.values()) + 1e-6
        rows.append(("DP optimal performs best in physics", ("all tied: " if tied else f"lowest: {best}; ") + listing,
                     "yes" if first and not tied else "no"))
        ok = not tied and all(errors[n] < min(errors["dp-base"], errors["rl"]) for n in ("L1", "L2"))
        rows.append(("lookahead generally outperforms DP baseline and RL in physics", listing, "yes" if ok else "no"))
        falls = sum(r["falls"] for r in b.values())
        total = sum(len(r["episodes"]) for r in b.values())
        if falls == total:
            rows.append(("the surrogate's reward is correlated with the physics outcome",
                         f"every policy dropped the tool in every episode ({falls}/{total}): no ranking in physics",
                         "no"))
    return rows


def fig4b_wall(results: dict) -> float:
    """Fig. 4b's wall time: in C MuJoCo the policies share one lockstep (each result carries its wall time), in
    MJX they run one after another."""
    walls = [r["wall_s_incl_compile"] for r in results.values()]
    return max(walls) if all(r.get("backend") == "c" for r in results.values()) else sum(walls)


def report(s: dict) -> str:
    stage = {"Fig. 4a": sum(s["fig4a"]["wall_s"].values()) if "fig4a" in s else None,
             "Table 1": s.get("table1", {}).get("wall_s"),
             "Fig. 4b": fig4b_wall(s["fig4b"]) if "fig4b" in s else None}
    times = ", ".join(f"{k} {v / 60:.1f} min" for k, v in stage.items() if v is not None)
    lines = [f"# gsp_jax: the paper's evaluation, reproduced ({s['preset']} preset)", "",
             f"Generated by `{s.get('command', 'python -m experiments reproduce --' + s['preset'])}` "
             f"on {s['device']}, {s['date']}. "
             f"Stage wall times, compilation included: {times}."
             + (f" {s['provenance']}" if s.get("provenance") else ""), ""]
    if "fig4a" in s:
        f = s["fig4a"]
        lines += ["## Fig. 4a: surrogate return relative to DP optimal", "",
                  f"{len(f['episodes'])} unseen evaluation episodes, stepped on the {f['backend']} backend; "
                  f"RL policy `{f['rl_policy']}`. "
                  f"Return - DP optimal return (0 is optimal; a fall costs {f['r_min']:g}).", "",
                  "![Fig. 4a](fig4a.png)", "",
                  "| policy | mean | 95% CI ± | optimal on | falls |", "|---|---|---|---|---|"]
        for n, r in f["relative"].items():
            lines.append(f"| {n} | {r['mean']:.3f} | {r['ci95']:.3f} | "
                         f"{r['optimal']}/{len(f['episodes'])} | {r['falls']} |")
        lines += ["", "```", f["anova_text"], "```", ""]
        if "table_vs_surrogate_max_abs" in f:
            worst = max(f["table_vs_surrogate_max_abs"].values())
            per = ", ".join(f"{n} {v:.2g}" for n, v in f["table_vs_surrogate_max_abs"].items())
            lines += [f"Cross-check, surrogate-stepped vs table-stepped returns, max |difference| per policy: {per}. "
                      "The tables are built by the same IK and wrench kernels, batched; on a CPU the two agree to "
                      "1e-5 (tests), on a GPU float32 reductions in the iterative solves differ in order, which moves "
                      "marginal rewards" + (f" (largest: {worst:.2g})." if worst > 1e-3 else "."), ""]
    if "table1" in s:
        t = s["table1"]
        batched = any("batch" in r for r in t["policies"].values())
        lines += ["## Table 1: online wall-clock time per unseen episode", "",
                  f"Ours on {t['device']} (episode `{t['episode']}`, "
                  f"warm = fastest of {t['repeats']} after compiling); "
                  f"paper on a {common.PAPER['table1_machine']}." + (f" Note: {t['note']}." if t.get("note") else ""),
                  "", "| | " + " | ".join(t["policies"]) + " |", "|---" * (len(t["policies"]) + 1) + "|",
                  "| paper [s] | " + " | ".join(f"{common.PAPER['table1_s'][n]:.2f}" for n in t["policies"]) + " |",
                  "| ours, warm [s] | " + " | ".join(f"{r['warm_s']:.4f}" for r in t["policies"].values()) + " |",
                  "| ours, compile [s] | " + " | ".join(f"{r['compile_s']:.1f}" for r in t["policies"].values()) + " |"]
        if batched:
            lines.append("| ours, per episode in a batch [s] | "
                         + " | ".join(f"{r['batch_per_episode_s']:.4f} (of {r['batch']})"
                                      for r in t["policies"].values()) + " |")
        lines.append("")
    if "fig4b" in s:
        b = s["fig4b"]
        n = len(next(iter(b.values()))["episodes"])
        engine = {"mjx": "MJX", "c": "C MuJoCo"}.get(next(iter(b.values())).get("backend", "mjx"), "MJX")
        lines += [f"## Fig. 4b: the same policies closed loop in physics ({engine})", "",
                  f"{n} unseen episodes; mean tool angle error under the final torque, 180° when the tool fell.", "",
                  "![Fig. 4b](fig4b.png)", "", "| policy | mean [deg] | 95% CI ± | fell | mean time of the fall [s] |",
                  "|---|---|---|---|---|"]
        for name, r in b.items():
            if planners.get(name).group == "verified":  # beyond the paper
                bases = " + ".join(r.get("bases", ["rl"]))  # results without them were k = 17 under RL
                name = f"{name} (k = {r.get('k', 17)}, branches under {bases}; not in the paper)"
            ci = "–" if not np.isfinite(r["ci95_deg"]) else f"{r['ci95_deg']:.1f}"
            times = [e["fall_time_s"] for e in r["per_episode"] if e["fell"]]
            when = f"{np.mean(times):.2f}" if times else "–"
            lines.append(f"| {name} | {r['mean_deg']:.1f} | {ci} | {r['falls']}/{len(r['episodes'])} | {when} |")
        lines.append("")
    claims = _claims(s)
    if claims:
        lines += ["## The paper's claims against these numbers", "", "| claim | ours | agrees |", "|---|---|---|"]
        lines += [f"| {c} | {o} | {a} |" for c, o, a in claims]
        lines.append("")
    return "\n".join(lines)
