"""`python -m experiments calibrate --learn [--model M]`: the model's learned physics term, from corpus to weights.

1. The model's physics corpus (`experiments.physics.corpus`: results/corpus[-<model>]/, or `--corpus`) extended to
   `--shards` shards; a corpus already there is reused (`--shards 0`: fit on what it holds).
2. The hazard (`gsp_jax.learned.fit`) on the transitions a planner can meet (`learned.surrogate_alive`) that physics
   reached, split by episode into train / validation / test, early stopping on validation.
3. Checks on the test episodes, never used in fitting: AUC of the run's predicted chance to hold, and of its
   return with and without the term (`learned.returns`), for hold against fall; the share of the sequences the
   surrogate calls feasible that hold, with and without; calibration per probability bin (`learned.reliability`);
   the hazard's AUC per sequence kind.
4. The weights beside the model's scene (`learned.path_of`, or `--out`), where `Surrogate(learned=True)` and
   `--learned` find them. Writes results/learn[-<model>]/report.json; prints the checks as a table last.
"""
from __future__ import annotations

import argparse
import pathlib
import time

import jax
import numpy as np

from experiments import common
from experiments.common import results_dir, table
from experiments.physics import corpus as corpus_cmd
from gsp_jax import files, learned, reward, stats
from gsp_jax import model as model_lib


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--corpus", nargs="+", default=None, metavar="FOLDER",
                   help="the corpus folders (default: results/corpus[-<model>], and results/corpus-learned[-...] "
                        "where `corpus --learned` made one: the learned planners' sequences)")
    p.add_argument("--out", default=None, help="where the weights go (default: beside the model's scene)")
    p.add_argument("--fit-seed", type=int, default=0, help="the split's and the network's seed")
    p.add_argument("--epochs", type=int, default=learned.FitConfig.epochs)


def _checks(data: dict, fitted: learned.Fitted, cfg: reward.RewardConfig) -> dict:
    """The test split's figures (see the module's docstring)."""
    test = np.isin(data["episode"], fitted.split["test"])
    x, fell = data["features"][test], data["fell"][test]
    p = np.asarray(jax.jit(learned.hazard)(fitted, x))  # (M, T)
    meet = data["alive"][test] & learned.surrogate_alive(x)
    hold_p = np.prod(np.where(learned.surrogate_alive(x), 1 - p, 1.0), 1)  # the chance to hold through
    plain, plain_ok = learned.returns(x, None, cfg)
    risky, risky_ok = learned.returns(x, p, cfg)
    kinds = data["kinds"][data["kind"][test]]
    out = dict(test_runs=int(test.sum()), test_episodes=len(fitted.split["test"]), test_falls=int(fell.sum()),
               auc_hold_chance=stats.auc(hold_p[~fell], hold_p[fell]),
               auc_return_analytic=stats.auc(plain[~fell], plain[fell]),
               auc_return_learned=stats.auc(risky[~fell], risky[fell]),
               feasible_analytic=int(plain_ok.sum()), feasible_hold_analytic=float(np.mean(~fell[plain_ok])),
               feasible_learned=int(risky_ok.sum()),
               feasible_hold_learned=float(np.mean(~fell[risky_ok])) if risky_ok.any() else float("nan"),
               transition_auc=stats.auc(p[meet & data["fell_here"][test]], p[meet & ~data["fell_here"][test]]),
               reliability=learned.reliability(p[meet], data["fell_here"][test][meet]))
    ep = data["episode"][test]
    out["pool_regret_analytic"], out["pool_regret_learned"], out["pool_holdable"] = (
        *(_pool_regret(score, fell, ep) for score in (plain, risky)), int(sum(not fell[ep == e].all()
                                                                            for e in np.unique(ep))))
    base = [k.rstrip("0123456789") for k in kinds]
    out["per_kind"] = {k: dict(runs=int(np.sum(np.array(base) == k)),
                               falls=int(fell[np.array(base) == k].sum()),
                               auc=stats.auc(hold_p[(np.array(base) == k) & ~fell],
                                             hold_p[(np.array(base) == k) & fell])) for k in sorted(set(base))}
    return out


def main(args: argparse.Namespace) -> None:
    model = model_lib.load_model()
    t0 = time.perf_counter()
    folders = args.corpus or [None]
    cargs = argparse.Namespace(folder=folders[0], shards=args.shards, first=0, episodes=args.episodes,
                               random=4, perturbed=2, steps=None, cores=None)
    stores = [corpus_cmd.build(cargs) if args.shards else learned_store(cargs, model)]
    if args.corpus is None:
        on_policy = common.RESULTS / corpus_cmd.folder_of(cargs).with_name(corpus_cmd.folder_of(cargs).name
                                                                          + "-learned").name
        folders += [on_policy] if (on_policy / "manifest.json").exists() else []
    stores += [learned_store(argparse.Namespace(folder=f), model) for f in folders[1:]]
    data = _joined([s.load() for s in stores])
    t_corpus = time.perf_counter() - t0
    meet = data["alive"] & learned.surrogate_alive(data["features"])
    print(f"learn: {len(data['fell'])} runs, {int(meet.sum())} transitions a planner meets, "
          f"{int(data['fell'].sum())} falls; fitting ...", flush=True)
    config = learned.FitConfig(epochs=args.epochs)
    fitted = learned.fit(data["features"], data["fell_here"], meet, data["episode"],
                         jax.random.PRNGKey(args.fit_seed), model.digest, learned.FEATURES, config, progress=True)
    t_fit = time.perf_counter() - t0 - t_corpus
    out = pathlib.Path(args.out) if args.out else learned.path_of(model)
    learned.save(fitted, out)
    cfg = reward.RewardConfig()
    checks = _checks(data, fitted, cfg)
    report = dict(model=model.name, digest=model.digest, weights=str(out), corpus=[str(s.folder) for s in stores],
                  shards=sum(len(s.manifest["shards"]) for s in stores), runs=int(len(data["fell"])),
                  epochs=len(fitted.history),
                  corpus_s=t_corpus, fit_s=t_fit, risk_falls=cfg.risk_falls, w_risk=cfg.w_risk, **checks)
    files.write_json(results_dir("learn") / "report.json", report)
    print(f"learn: weights in {out}; report in {results_dir('learn') / 'report.json'}", flush=True)
    print(table(["reliability bin", "transitions", "predicted", "observed"],
                [[f"{b['low']:.1f}-{b['high']:.1f}", b["n"], b["predicted"], b["observed"]]
                 for b in checks["reliability"] if b["n"]]))
    rows = [["test runs (episodes)", f"{checks['test_runs']} ({checks['test_episodes']})"],
            ["falls", checks["test_falls"]],
            ["AUC, predicted chance to hold", checks["auc_hold_chance"]],
            ["AUC, return: analytic", checks["auc_return_analytic"]],
            ["AUC, return: with the term", checks["auc_return_learned"]],
            ["feasible that hold: analytic", f"{100 * checks['feasible_hold_analytic']:.1f}% of "
                                              f"{checks['feasible_analytic']}"],
            ["feasible that hold: with the term", f"{100 * checks['feasible_hold_learned']:.1f}% of "
                                                   f"{checks['feasible_learned']}"],
            ["AUC per transition", checks["transition_auc"]],
            ["best of the episode's runs fell, another held: analytic return",
             f"{checks['pool_regret_analytic']} of {checks['pool_holdable']}"],
            ["the same: return with the term", f"{checks['pool_regret_learned']} of {checks['pool_holdable']}"],
            ["corpus, fit [s]", f"{t_corpus:.0f}, {t_fit:.0f}"]]
    common.record("learned_term", {k: v for k, v in report.items() if k not in ("reliability",)})
    print(table([f"learned physics term, {model.name}", "test split"], rows))


def _pool_regret(score: np.ndarray, fell: np.ndarray, episode: np.ndarray) -> int:
    """Episodes where the run of the highest score fell while another run of the episode held: a planner's regret
    when it chooses among the corpus's sequences by `score`."""
    return int(sum(fell[s][np.argmax(score[s])] for e in np.unique(episode)
                   if not fell[s := episode == e].all()))


def _joined(parts: list[dict]) -> dict:
    """Corpora's arrays as one (episode ids renumbered past the earlier corpora's)."""
    offset, out = 0, []
    for part in parts:
        out.append(dict(part, episode=part["episode"] + offset))
        offset += len(part["episode_names"])
    return {k: np.concatenate([p[k] for p in out]) for k in out[0]}


def learned_store(cargs: argparse.Namespace, model):
    from gsp_jax.physics import corpus

    folder = corpus_cmd.folder_of(cargs)
    try:
        return corpus.Store.open(folder, model)
    except corpus.CorpusError as e:
        raise SystemExit(f"calibrate --learn: {e}") from None
