"""FlowMaps beside SGM's agents on SGM's simulator (issue 56, item 5).

    python experiments/peers/sgm.py --sgm PATH --sgm-python PY --out DIR \\
        [--scenes small,large] [--steps N] [--seeds 0] [--train-sim-steps N] [--train-steps N]
        [--allowed all|training]

SGM ("Modeling Dynamic Environments with Scene Graph Memory", Kurenkov et al., ICML 2023) is
andreykurenkov/modeling_env_dynamics, GPL-3: it runs from the checkout ``--sgm`` under its own
Python ``--sgm-python`` (numpy, scipy, networkx, hydra-core, omegaconf, coloredlogs, matplotlib,
tqdm, tensorboardX, pyyaml; no torch: the graph-network agents are not run), through
``sgm_driver.py`` (which applies the three runtime fixes; nothing of SGM is copied here).

For each scene size: the driver runs SGM's six non-learning agents on the evaluation seeds in
their own protocol (each agent looks where it predicted) and in the shared-observer one (one
uniform look per step, the same for every agent; written as a log in ``import-log``'s schema,
one simulator step = one hour, a scene = an environment, hours 0 … eps_per_scene − 1); it also
writes a training log of other seeds (``--train-seed`` on). The logs are split into
environments of at most ``MAX_OBJECTS`` objects each (``<scene>/part<j>``: every look is copied
to every part; the homes network takes at most that many objects), converted with
``python -m flowmaps_jax.data import-log``, FlowMaps trains on the training log
(``python -m flowmaps_jax.train --data``, the default recipe, ``--train-steps``) and answers
every shared query at τ_q = its hour from the log up to τ = τ_q − 1 (the look of τ_q comes after
the query, as in SGM's loop). SGM's accuracy: the share of queries whose predicted receptacle
holds an object of the query's description; FlowMaps and the count rows predict their most
probable receptacle; an evaluation object may be on any receptacle of its scene (``--allowed
training``: only on classes the training log saw its class on). A query a row cannot read (hour
0, an object never seen in the whole log, a class the training log never showed, a scene larger
than any trained on) gets :func:`log_fallback`'s guess from the logs (last seen, else the class
frequency), counted in the table. Writes ``DIR/results.md`` (printed) and ``DIR/results.json``.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import json
import math
import os
import pathlib
import shlex
import subprocess
import sys
from collections import defaultdict

import numpy as np

AGENTS = ("random", "priors", "memorization", "frequentist", "bayesian", "upper_bound")
DRIVER = pathlib.Path(__file__).with_name("sgm_driver.py")
P_FLOOR = 1e-9
FALLBACK_ROW = "last seen, else class frequency"
"""The row that answers every query with :func:`log_fallback`."""
MAX_OBJECTS = 15
"""The homes network's objects per environment (flowmaps_jax.flowsim.homes.config)."""


def check_sgm(path) -> pathlib.Path:
    """``path`` as a checkout of SGM, or ``ValueError`` naming ``--sgm``."""
    root = pathlib.Path(path)
    if not root.is_dir():
        raise ValueError(f"--sgm: {path} is not a folder (a checkout of "
                         f"andreykurenkov/modeling_env_dynamics)")
    for need in ("memsearch/scene.py", "memsearch/agents.py", "configs/scene_gen/small_scenes.yaml",
                 "priors/detailed_prior_graph.pickle"):
        if not (root / need).is_file():
            raise ValueError(f"--sgm: {path} is not a checkout of SGM "
                             f"(andreykurenkov/modeling_env_dynamics): it has no {need}")
    return root.resolve()


def read_csv(path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def write_csv(path, rows: list[dict], columns=None) -> None:
    tmp = pathlib.Path(str(path) + ".tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns or list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)


def split_log(rows: list[dict], max_objects: int = MAX_OBJECTS) -> tuple[list[dict], dict]:
    """(rows, part): the log with each environment split into ``<env>/part<j>`` environments of
    at most ``max_objects`` objects each (sorted ids, parts as even as can be), every
    object-less row (a look) copied to every part; ``part[(env, object)]`` names the object's."""
    objects = defaultdict(set)
    for r in rows:
        if r["object"]:
            objects[r["environment"]].add(r["object"])
    part, parts = {}, {}
    for env, ids in objects.items():
        ids = sorted(ids)
        n = math.ceil(len(ids) / max_objects)
        parts[env] = [f"{env}/part{j}" for j in range(n)]
        for i, o in enumerate(ids):
            part[env, o] = parts[env][i * n // len(ids)]
    out = []
    for r in rows:
        if r["object"]:
            out.append({**r, "environment": part[r["environment"], r["object"]]})
        else:
            out += [{**r, "environment": p} for p in parts.get(r["environment"], ())]
    return out, part


def sgm_accuracy(predicted: list[str], correct: list[str]) -> float:
    """SGM's metric: the share of queries whose prediction is among the receptacles holding an
    object of the query's description (``correct``: ';'-joined ids)."""
    hits = [p in c.split(";") for p, c in zip(predicted, correct, strict=True)]
    return float(np.mean(hits)) if hits else float("nan")


def class_pairs(recorded) -> set:
    """(object class, receptacle class) of every sighting in ``recorded``."""
    pairs = set()
    for env in recorded.environments:
        t, m = np.nonzero(np.asarray(env.location) >= 0)
        r = np.asarray(env.location)[t, m]
        pairs |= {(env.object_classes[i], env.receptacle_classes[j])
                  for i, j in zip(m, r, strict=True)}
    return pairs


def readable(recorded, config, pairs: set | None = None) -> tuple[list, int]:
    """``recorded``'s environments as the model can read them without the future: objects of
    classes ``config`` lacks removed (environments with such receptacle or room classes, larger
    than ``config``'s homes, or with no object left, dropped), ``allowed`` every receptacle, or
    with ``pairs`` the training log's class pairs (every receptacle for an object with none; a
    sighting outside them counts as unseen; import-log's own allowed comes from this log's
    sightings, future ones included); and the number of objects removed."""
    voc = {f: {c.text for c in getattr(config, f)} for f in
           ("object_classes", "receptacle_classes", "room_types")}
    envs, removed = [], 0
    for env in recorded.environments:
        keep = np.asarray([c in voc["object_classes"] for c in env.object_classes])
        removed += int((~keep).sum())
        rooms = len(env.room_classes) + bool(np.any(np.asarray(env.receptacle_room) < 0))
        if not keep.any() or not set(env.receptacle_classes) <= voc["receptacle_classes"] \
                or not set(env.room_classes) <= voc["room_types"] \
                or env.num_receptacles > config.max_receptacles or rooms > config.num_rooms \
                or int(env.hours[-1]) >= config.num_hours:
            removed += int(keep.sum())
            continue
        pick = functools.partial(_keep, keep)
        classes = pick(env.object_classes)
        allowed = np.asarray([[pairs is None or (o, r) in pairs for r in env.receptacle_classes]
                              for o in classes]).reshape(len(classes), -1)
        allowed[~allowed.any(1)] = True
        location = pick(env.location)
        location = np.where(allowed[np.arange(len(classes)), np.maximum(location, 0)],
                            location, -1)  # a sighting on a receptacle not allowed: unseen
        envs.append(dataclasses.replace(
            env, object_ids=pick(env.object_ids), object_classes=classes,
            object_texts=pick(env.object_texts), allowed=allowed,
            location=location.astype(env.location.dtype), not_at=pick(env.not_at),
            object_corners=pick(env.object_corners), object_rotation=pick(env.object_rotation)))
    return envs, removed


def _keep(keep, a, axis=1):
    """``a`` (a tuple of names, or an array along ``axis``) where ``keep``."""
    if isinstance(a, tuple):
        return tuple(x for x, k in zip(a, keep, strict=True) if k)
    return None if a is None else np.compress(keep, a, axis)


def allow_everywhere(source, target, everywhere: bool) -> None:
    """The dataset ``source`` written to ``target``, with every object allowed on every
    receptacle of its environment if ``everywhere`` (import-log allows only the class pairs
    its log sighted, so a model trained on it never learns the moves that log did not show)."""
    from flowmaps_jax.recorded.format import Recorded, load_recorded, save_recorded

    envs = load_recorded(str(source)).environments
    if everywhere:
        envs = [dataclasses.replace(e, allowed=np.ones_like(e.allowed)) for e in envs]
    save_recorded(Recorded(tuple(envs)), str(target))


def flowmaps_rows(run_dir, train_data, eval_data, queries: list[dict], part: dict,
                  batch: int = 16, allowed: str = "all") -> dict:
    """{row: (probabilities {receptacle id: p} or None per query)} for FlowMaps and the
    reference rows (count rows fitted on the run's training part at horizon 1, the queries'),
    None where the row cannot read the query; ``removed``: objects of unknown classes."""
    import jax.numpy as jnp

    from flowmaps_jax.evaluation import realised
    from flowmaps_jax.flowsim.homes.queries import HomesQueries
    from flowmaps_jax.predictor import load_model, stored_run
    from flowmaps_jax.recorded.format import Recorded, load_recorded
    from flowmaps_jax.worlds import recorded as rw

    predictor = load_model(str(run_dir))
    _, stored = stored_run(str(run_dir))
    train, _ = rw.load_data(str(train_data))
    *_, train_part = realised.evaluation_part(train, predictor.homes, stored, str(train_data))
    fit = realised.fit_counts(train_part, predictor.homes, predictor.model.history, 1)
    envs, removed = readable(load_recorded(str(eval_data)), predictor.homes,
                             class_pairs(train) if allowed == "training" else None)
    recorded = Recorded(tuple(envs))
    index = {e.name: i for i, e in enumerate(envs)}
    asked = defaultdict(list)  # env index -> [(query number, object slot, hour)]
    for n, q in enumerate(queries):
        name, hour = part.get((q["environment"], q["object"])), int(q["timestamp"])
        env = envs[index[name]] if name in index else None
        if env is not None and 0 < hour <= min(env.hours[-1] + 1, predictor.homes.num_hours - 1) \
                and q["object"] in env.object_ids:
            asked[index[name]].append((n, env.object_ids.index(q["object"]), hour))
    out = defaultdict(lambda: [None] * len(queries))
    width = max((len(v) for v in asked.values()), default=1)
    order = sorted(asked)
    for start in range(0, len(order), batch):
        chunk = order[start:start + batch]
        chunk += chunk[-1:] * (batch - len(chunk))  # one shape: one compilation
        data = rw.recorded_homes(recorded, predictor.homes, index=chunk)
        cols = np.zeros((3, len(chunk), width), np.int32)
        cols[1], cols[2] = 0, 1
        for row, e in enumerate(chunk):
            for col, (_, obj, hour) in enumerate(asked[e]):
                cols[:, row, col] = obj, hour - 1, hour
        queries_ = HomesQueries(*(jnp.asarray(c) for c in cols))
        for name, p in realised.row_probabilities(predictor, data, queries_, fit).items():
            p = np.asarray(p)
            for row, e in enumerate(chunk):
                ids = envs[e].receptacle_ids
                for col, (n, _, _) in enumerate(asked[e]):
                    out[name][n] = {ids[r]: float(p[row, col, r]) for r in range(len(ids))}
    return {"rows": dict(out), "removed": removed, "step": predictor.step}


def log_fallback(queries: list[dict], trace: list[dict], train: list[dict]) -> list[dict]:
    """For each query, a guess from the logs alone: with probability ``stay`` where the object
    was last seen before the query's hour (``trace``, the evaluation log), else (and for an
    object never seen) the training log's frequency of the object's class on each receptacle
    class of the scene (add-one; all classes pooled for a class it never showed). ``stay``: the
    share of the training log's consecutive sightings of an object on the same receptacle."""
    pairs, per_class, last, stays = defaultdict(float), defaultdict(float), {}, []
    for r in train:
        if r["object"]:
            pairs[r["object_class"], r["receptacle_class"]] += 1
            per_class[r["receptacle_class"]] += 1
            key = (r["environment"], r["object"])
            if key in last:
                stays.append(last[key] == r["receptacle"])
            last[key] = r["receptacle"]
    stay = float(np.mean(stays)) if stays else 0.5
    known = {o for o, _ in pairs}
    scene, seen = defaultdict(dict), defaultdict(list)  # env -> {receptacle: class}; sightings
    for r in trace:
        scene[r["environment"]][r["receptacle"]] = r["receptacle_class"]
        if r["object"]:
            seen[r["environment"], r["object"]].append((int(r["timestamp"]), r["receptacle"]))
    out = []
    for q in queries:
        receptacles, hour = scene[q["environment"]], int(q["timestamp"])
        counts = {r: 1 + (pairs[q["object_class"], c] if q["object_class"] in known
                          else per_class[c]) for r, c in receptacles.items()}
        total = sum(counts.values())
        guess = {r: n / total for r, n in counts.items()}
        before = [r for h, r in seen[q["environment"], q["object"]] if h < hour]
        if before:
            guess = {r: (1 - stay) * p + stay * (r == before[-1]) for r, p in guess.items()}
        out.append(guess)
    return out


def score_row(answers: list, queries: list[dict], fallback: list[dict]) -> dict:
    """SGM accuracy (the most probable receptacle; first on ties) and the mean log score of the
    query object's receptacle over ``answers``; a query without an answer gets its
    ``fallback`` guess (:func:`log_fallback`)."""
    acc, logs, used = [], [], 0
    for a, q, guess in zip(answers, queries, fallback, strict=True):
        correct = [q["receptacle"], *(c for c in q["receptacles"].split(";")
                                      if c != q["receptacle"])]
        if a is None:
            a, used = guess, used + 1
        best = max(a, key=a.get)
        acc.append(float(best in correct))
        logs.append(math.log(max(a.get(correct[0], 0.0), P_FLOOR)))
    return {"accuracy": float(np.mean(acc)), "log_score": float(np.mean(logs)),
            "fallback": used}


def sh(cmd: list[str], log, **kw) -> None:
    """Runs ``cmd`` niced, its output to ``log``; ``RuntimeError`` with its tail on failure."""
    print("$", shlex.join(cmd), flush=True)
    with open(log, "a") as f:
        done = subprocess.run(["nice", "-n", "19", *cmd], stdout=f, stderr=subprocess.STDOUT, **kw)
    if done.returncode:
        tail = pathlib.Path(log).read_text().splitlines()[-15:]
        raise RuntimeError(f"{cmd[0]} … exited {done.returncode}; {log}:\n" + "\n".join(tail))


def run_scenes(args, scenes: str, out: pathlib.Path) -> dict:
    """Everything for one scene size; returns its results."""
    out.mkdir(parents=True, exist_ok=True)
    log = out / "log.txt"
    driver = [args.sgm_python, str(DRIVER), "--sgm", str(args.sgm), "--scenes", scenes]
    queries, own, shared, trace = [], defaultdict(list), defaultdict(list), []
    for seed in args.seeds:
        d = out / f"eval-s{seed}"
        if not (d / "driver.json").is_file():
            sh([*driver, "--seed", str(seed), "--out", str(d), "--prefix", f"{scenes}-s{seed}-",
                         "--observation-prob", str(args.observation_prob),
                         *(["--steps", str(args.steps)] if args.steps else [])], log)
        result = json.loads((d / "driver.json").read_text())
        for k in ("own", "shared"):
            for a, v in result.get(k, {}).items():
                (own if k == "own" else shared)[a].append(v)
        queries += read_csv(d / "queries.csv")
        trace += read_csv(d / "trace.csv")
    t = out / "train-sim"
    if not (t / "driver.json").is_file():
        sh([*driver, "--seed", str(args.train_seed), "--out", str(t), "--agents", "",
                     "--protocols", "shared", "--steps", str(args.train_sim_steps),
                     "--prefix", f"{scenes}-train-", "--observation-prob",
                     str(args.observation_prob)], log)
    datasets = {}
    for name, rows in (("train", read_csv(t / "trace.csv")), ("eval", trace)):
        table, part = split_log(rows)
        if name == "eval":
            eval_part = part
        path = out / f"{name}_log.csv"
        write_csv(path, table)
        datasets[name] = out / f"{name}_data"
        if not (datasets[name] / "recorded.json").is_file():
            sighted = out / f"{name}_data_sighted"
            sh([sys.executable, "-m", "flowmaps_jax.data", "import-log", str(path), "--out",
                str(sighted), "--no-progress"], log)
            allow_everywhere(sighted, datasets[name], args.allowed == "all")
    run_dir = out / "run"
    if not (run_dir / "checkpoints").is_dir():
        sh([sys.executable, "-m", "flowmaps_jax.train", "--data", str(datasets["train"]),
            "--run-dir", str(run_dir), "--steps", str(args.train_steps), "--no-progress",
            *(["--set", f"warmup_steps={args.train_steps // 5}"] if args.train_steps <= 200
              else [])], log)  # a smoke run: the recipe's warm-up (200 steps) shortened
    answers = flowmaps_rows(run_dir, datasets["train"], datasets["eval"], queries, eval_part,
                            allowed=args.allowed)
    fallback = log_fallback(queries, trace, read_csv(t / "trace.csv"))
    answers["rows"][FALLBACK_ROW] = [None] * len(queries)
    rows = {a: {"own": float(np.mean(own[a])) if own.get(a) else None,
                "shared": sgm_accuracy([q[a] for q in queries],
                                       [q["receptacles"] for q in queries])}
            for a in shared}
    for name, ans in answers["rows"].items():
        rows[name] = {"own": None, **score_row(ans, queries, fallback)}
    return {"queries": len(queries), "objects_of_unknown_class": answers["removed"],
            "flowmaps_step": answers["step"], "rows": rows}


def markdown(results: dict) -> str:
    lines = []
    for scenes, r in results["scenes"].items():
        lines += [f"`{r['command']}`", "",
                  f"**{scenes} scenes** ({r['queries']} queries; FlowMaps at step "
                  f"{r['flowmaps_step']}; {r['objects_of_unknown_class']} evaluation objects of "
                  "classes the training log never showed)", "",
                  "| agent | SGM accuracy, own looks | SGM accuracy, shared looks | log score "
                  "(nats) | log fallbacks |", "| --- | --- | --- | --- | --- |"]
        for name, row in r["rows"].items():
            f = lambda v, d=3: "–" if v is None else f"{v:.{d}f}"  # noqa: E731
            lines.append(f"| {name} | {f(row.get('own'))} | "
                         f"{f(row.get('shared', row.get('accuracy')))} | "
                         f"{f(row.get('log_score'))} | {row.get('fallback', '–')} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sgm", required=True,
                   help="a checkout of andreykurenkov/modeling_env_dynamics")
    p.add_argument("--sgm-python", default=sys.executable, help="the Python that runs SGM")
    p.add_argument("--out", required=True)
    p.add_argument("--scenes", default="small,large")
    p.add_argument("--steps", type=int, default=None, help="simulator steps per evaluation seed "
                   "(default: the config's, 11,000)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--train-seed", type=int, default=1000)
    p.add_argument("--train-sim-steps", type=int, default=22000)
    p.add_argument("--train-steps", type=int, default=1500)
    p.add_argument("--observation-prob", type=float, default=1.0)
    p.add_argument("--allowed", choices=("all", "training"), default="all",
                   help="where an evaluation object may be: every receptacle of its scene, or "
                   "those of the classes the training log saw its class on")
    args = p.parse_args(argv)
    try:
        args.sgm = check_sgm(args.sgm)
        scenes = [s for s in args.scenes.split(",") if s]
        if not scenes or set(scenes) - {"small", "large"}:
            raise ValueError(f"--scenes must list small and/or large; got {args.scenes!r}")
    except ValueError as err:
        p.error(str(err))
    out = pathlib.Path(args.out)
    command = "python experiments/peers/sgm.py " + shlex.join(sys.argv[1:] if argv is None
                                                               else list(argv))
    path = out / "results.json"  # one file for every scene size run into --out
    results = json.loads(path.read_text()) if path.is_file() else {"scenes": {}}
    for s in scenes:
        results["scenes"][s] = {"command": command, **run_scenes(args, s, out / s)}
    path.write_text(json.dumps(results, indent=1))
    text = markdown(results)
    (out / "results.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
