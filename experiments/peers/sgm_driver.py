"""Runs SGM's simulator and agents (Kurenkov et al., ICML 2023;
andreykurenkov/modeling_env_dynamics, GPL-3) from a checkout, under that checkout's own Python;
started by ``experiments/peers/sgm.py``.
Nothing of SGM is copied here: its modules are imported from ``--sgm`` and three runtime fixes are
applied by rebinding names in them (their files are not edited):

1. ``random.choices`` refuses all-zero weights on Python >= 3.9: such a draw is uniform instead;
2. child / parent lists are built from sets of nodes hashed by address, and unique ids are
   ``uuid4``: ids come from a counter and the lists are sorted by id, so a seed fixes a run;
3. agents and environment share the ``random`` module: the environment (scene sampling,
   evolution, queries, the observer) draws from its own seeded stream and every agent from its
   own, so every agent sees the same scene sequence.

Two protocols on one scene sequence (``--seed``):

* ``own`` (SGM's ``predict_location`` as their ``running.run`` does it): each agent predicts
  the query's furniture and then observes the furniture it predicted (each object on it kept
  with probability ``agents.observation_prob``); accuracy = the share of correct predictions;
* ``shared``: the same queries, but one observer looks at one furniture per step (uniform; each
  object on it seen with probability ``--observation-prob``) and every agent receives that same
  observation after predicting. The trace is written in the import-log schema (``trace.csv``,
  one step = one hour, hour h of scene k at timestamp h of environment k) with the queries and
  each agent's prediction (``queries.csv``).
"""

import argparse
import csv
import functools
import importlib.util
import json
import logging
import os
import random
import sys
import time
import types
import uuid

NON_LEARNING = ("random", "priors", "memorization", "frequentist", "bayesian", "upper_bound")
IDS = [iter(())]
"""The unique-id counter (reset by each :class:`Run`)."""
TRACE_COLUMNS = ("environment", "timestamp", "object", "object_class", "receptacle",
                 "receptacle_class", "room", "found")


class Stream(random.Random):
    """A seeded stream standing in for the ``random`` module (``Random`` kept for
    ``random.Random()`` calls)."""
    Random = random.Random


def choose(stream):
    """``sample_from_dict`` on ``stream``; all-zero weights draw uniformly (fix 1)."""
    def sample_from_dict(d):
        keys, weights = list(d.keys()), [float(w) for w in d.values()]
        if not sum(weights) > 0:
            return stream.choice(keys)
        return stream.choices(keys, weights=weights, k=1)[0]
    return sample_from_dict


def _stub(name):
    module = types.ModuleType(name)
    module.__path__ = []
    module.__getattr__ = lambda attr: None if attr.startswith("__") else object
    return module


def import_sgm(path):
    """SGM's modules with fixes 1 and 2, torch-free: the learning agents' modules (and gym, whose
    ``Env`` base class is all it is used for, when not installed) are stubbed."""
    os.chdir(path)  # its priors are read from relative paths
    sys.path.insert(0, path)
    for name in ("torch", "torch_geometric", "torch_geometric.transforms",
                 "torch_geometric.transforms.to_undirected", "memsearch.models",
                 "memsearch.dataset", *(() if importlib.util.find_spec("gym") else ("gym",))):
        sys.modules.setdefault(name, _stub(name))
    from memsearch import agents, graphs, scene, tasks, util

    graphs.uuid = types.SimpleNamespace(uuid4=lambda: uuid.UUID(int=next(IDS[0])))

    def related(pick):
        def nodes(self):
            found = {id(n): n for e in self.edges for n in [pick(self, e)] if n is not None}
            return sorted(found.values(), key=lambda n: n.unique_id)
        return nodes
    graphs.Node.get_children_nodes = related(lambda s, e: e.node2 if e.node1 is s else None)
    graphs.Node.get_parent_nodes = related(lambda s, e: e.node1 if e.node2 is s else None)
    graphs.Node.get_neighbor_nodes = related(lambda s, e: e.node2)
    return types.SimpleNamespace(agents=agents, graphs=graphs, scene=scene, tasks=tasks, util=util)


def use_streams(sgm, env, agent):
    """Fix 3: the environment's modules draw from ``env``, the agents' from ``agent``."""
    for module in (sgm.graphs, sgm.scene, sgm.tasks, sgm.util):
        module.random = env
        module.sample_from_dict = choose(env)
    sgm.agents.random = agent
    sgm.agents.sample_from_dict = choose(agent)


def load_config(path, scenes):
    import yaml
    from omegaconf import OmegaConf
    read = lambda *p: yaml.safe_load(open(os.path.join(path, "configs", *p)))  # noqa: E731
    cfg = {**read("scene_gen", f"{scenes}_scenes.yaml"), **read("agents", "all.yaml"),
           **read("task", "predict_location.yaml")}
    return OmegaConf.create(cfg)


class Run:
    """One scene sequence of ``seed``: the sampler, evolver and task, and the agents."""

    def __init__(self, sgm, cfg, seed, agent_types):
        IDS[0] = iter(range(1, 1 << 62))
        self.sgm, self.env = sgm, Stream(seed)
        self.agent_streams = [Stream(f"{seed}/{a}") for a in agent_types]
        use_streams(sgm, self.env, self.agent_streams[0] if agent_types else Stream(0))
        sampler, evolver = sgm.scene.make_scene_sampler_and_evolver(cfg.scene_gen)
        self.task = sgm.tasks.make_task(sampler, evolver, sgm.tasks.TaskType.PREDICT_LOC,
                                        eps_per_scene=cfg.task.eps_per_scene)
        self.agents = [sgm.agents.make_agent(cfg.agents, a, sgm.tasks.TaskType.PREDICT_LOC,
                                             scene_sampler=sampler, scene_evolver=evolver)
                       for a in agent_types]

    def agent(self, i):
        use_streams(self.sgm, self.env, self.agent_streams[i])
        return self.agents[i]

    def steps(self, num_steps):
        """Yields (scene number, hour in the scene, scene, query) per step; the caller's agents
        act between yields (SGM's loop: predict, observe, then the next evolution and query)."""
        query, scene, k, hour = self.task.reset(), None, -1, 0
        for _ in range(num_steps):
            if self.task.scene is not scene:
                scene, k, hour = self.task.scene, k + 1, 0
                for i in range(len(self.agents)):
                    self.agent(i).transition_to_new_scene(scene)
            yield k, hour, scene, query
            query, hour = self.task.reset(), hour + 1
            for i in range(len(self.agents)):
                self.agent(i).step()


def name(node):
    """A node's id in the tables: ``<label>|<counter>``."""
    return f"{node.label}|{uuid.UUID(node.unique_id.split(' ')[-1]).int}"


def room_of(sgm, node):
    while node.type != sgm.graphs.NodeType.ROOM:
        node = node.get_parent_node()
    return node.label


def run_own(sgm, cfg, seed, agent_types, num_steps):
    """SGM's protocol: {agent: accuracy}, each agent on its own run of the same scene sequence."""
    out = {}
    for a in agent_types:
        run, total = Run(sgm, cfg, seed, [a]), 0.0
        for _, _, scene, query in run.steps(num_steps):
            prediction = run.agent(0).make_predictions(sgm.tasks.TaskType.PREDICT_LOC, scene, query)
            obs, score, _, _ = run.task.step(prediction)
            run.agent(0).receive_observation(obs)
            total += float(score)
        out[a] = total / num_steps
    return out


def run_shared(sgm, cfg, seed, agent_types, num_steps, observation_prob, prefix, out_dir):
    """The shared-observer protocol; writes trace.csv and queries.csv, returns {agent: accuracy}."""
    furniture_type, object_type = sgm.graphs.NodeType.FURNITURE, sgm.graphs.NodeType.OBJECT
    run, correct = Run(sgm, cfg, seed, agent_types), [0.0] * len(agent_types)
    observer = Stream(f"{seed}/observer")
    for agent in run.agents:
        agent.observation_prob = 1.0  # the observer's draw is the one every agent receives
    trace_rows, query_rows = [], []
    for k, hour, scene, query in run.steps(num_steps):
        env_name = f"{prefix}{k:04d}"
        furniture = scene.scene_graph.get_nodes(furniture_type)
        truth = [name(f) for f in furniture if any(
            c.description == query.description for c in f.get_children_nodes())]
        row = {"environment": env_name, "timestamp": hour, "object": name(query),
               "object_class": query.label, "receptacle": name(query.get_parent_node()),
               "receptacles": ";".join(truth)}
        for i in range(len(run.agents)):
            prediction = run.agent(i).make_predictions(sgm.tasks.TaskType.PREDICT_LOC, scene, query)
            _, score, _, _ = run.task.step(prediction)
            correct[i] += float(score)
            row[agent_types[i]] = name(prediction)
        query_rows.append(row)
        looked = observer.choice(furniture)
        seen = [c for c in looked.get_children_nodes()
                if c.type == object_type and observer.random() < observation_prob]
        where = dict(receptacle=name(looked), receptacle_class=looked.label,
                     room=room_of(sgm, looked), environment=env_name, timestamp=hour)
        trace_rows.append({**where, "object": "", "object_class": "", "found": "false"})
        trace_rows += [{**where, "object": name(o), "object_class": o.label, "found": "true"}
                       for o in seen]
        looked.get_children_nodes = functools.partial(list, seen)
        for i in range(len(run.agents)):
            run.agent(i).receive_observation(looked)
        del looked.get_children_nodes
    write_csv(os.path.join(out_dir, "trace.csv"), TRACE_COLUMNS, trace_rows)
    write_csv(os.path.join(out_dir, "queries.csv"),
              ("environment", "timestamp", "object", "object_class", "receptacle", "receptacles",
               *agent_types),
              query_rows)
    return {a: c / num_steps for a, c in zip(agent_types, correct, strict=True)}


def write_csv(path, columns, rows):
    tmp = path + ".tmp"
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sgm", required=True)
    p.add_argument("--scenes", choices=("small", "large"), default="small")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=None, help="default: the config's num_steps")
    p.add_argument("--agents", default=",".join(NON_LEARNING), help="comma-separated; '' none")
    p.add_argument("--protocols", default="own,shared")
    p.add_argument("--observation-prob", type=float, default=1.0)
    p.add_argument("--prefix", default="scene")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    logging.getLogger().setLevel(logging.ERROR)  # SGM warns on every failed move draw
    sgm = import_sgm(os.path.abspath(args.sgm))
    cfg = load_config(os.path.abspath(args.sgm), args.scenes)
    steps = args.steps or int(cfg.task.num_steps)
    agent_types = [a for a in args.agents.split(",") if a]
    result = {"scenes": args.scenes, "seed": args.seed, "steps": steps,
              "eps_per_scene": int(cfg.task.eps_per_scene),
              "observation_prob": args.observation_prob,
              "agents_observation_prob": float(cfg.agents.observation_prob)}
    for protocol in args.protocols.split(","):
        start = time.process_time()
        if protocol == "own":
            result["own"] = run_own(sgm, cfg, args.seed, agent_types, steps)
        elif protocol == "shared":
            result["shared"] = run_shared(sgm, cfg, args.seed, agent_types, steps,
                                          args.observation_prob, args.prefix, out)
        else:
            p.error(f"--protocols: unknown protocol {protocol!r}")
        result[f"{protocol}_cpu_s"] = round(time.process_time() - start, 1)
    with open(os.path.join(out, "driver.json"), "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
