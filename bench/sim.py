"""Simulator benchmark: in-process step+render rate vs the distributed lock-step round trip.

Everything runs in one invocation on the same machine. `swimm router` starts first; then each way of serving
is measured in turn, with only its own two processes running besides the router: a `swimm sim` and a learner
process (this module run as a script). The learner takes the steps in rounds, each round a block of steps on
a World of its own, in its own process, and the same block through the sim, back to back. A virtual machine's
speed drifts by a third within a minute; measured in rounds, a way's served blocks and the in-process blocks
they alternate with see the same drift, so each way's ratio compares like with like. The four ways:

- peer, polling (the headline keys): the sim and the learner join as Zenoh peers (the router introduces
  them, each message goes directly from one to the other) with Zenoh's low-latency setting
  (``--low-latency``: its low-latency transport, one Zenoh thread a process), and each side polls for the
  next message for :data:`POLL_MS` before napping between looks (`swimm sim --poll-ms`,
  ``ProxySettings.poll_ms``): how to serve one env when each process has a core to itself;
- peer, polling, standard Zenoh (the ``standard_*`` keys): the same with Zenoh's defaults, which shows what
  the low-latency setting adds;
- peer, blocking (the ``blocking_*`` keys): Zenoh's defaults, each side sleeping on its inbox at once, as
  `swimm up` runs (there the processes share the cores with a training learner and the encoders);
- client (the ``routed_*`` keys; what deploy/docker-compose.yml runs): every message goes through the router,
  both sides blocking.

Each adds the msgpack codec, the Zenoh hops and the process switches to the in-process step, nothing else.
One way at a time, because the others' idle processes are not idle enough: a polling sim that has run out of
poll time still wakes every millisecond to look for work (services/polling.py), which slows the way measured
(docs/benchmarks.md). In a process of its own, each way's learner
also gets the Zenoh threads its setting asks for, which a process fixes when it opens its first session.

Before the ways, the scenery's cost (the ``plain_*``/``varied_*`` keys): the plain world and the varied one
(sim_service/scenery.py) step in-process, one :data:`SCENERY_EPISODE_STEPS`-step episode each in turn, so the
varied rate averages over many drawn scenes. Then what drawing anti-aliased costs (the ``render_*`` keys):
the plain world drawn at :data:`ANTI_ALIASED_SCALE` times the image size and area-downsampled, against the same
world drawn as always, in turn. Then what sharing one renderer is worth (the ``*_renderer*`` keys): a
sim's group of :data:`SHARED_RENDERER_ENVS` Worlds stepped round-robin in-process, with a renderer each and with
one shared, in turn.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.layout import default_layout
from learner_service.link import EnvLink, new_holder_id
from learner_service.up import sim_shares
from services.keys import Keys
from services.polling import POLLING_SWITCH_INTERVAL_S
from services.presence import Roster, announce
from services.process import DEFAULT_RENDER_THREADS, ProcessSettings, child_environment, configure_process
from services.procs import ProcessGroup, Service, zenoh_flags
from services.session import open_session
from services.settings import ZenohSettings
from sim_service.scenery import SceneSettings
from sim_service.settings import WorldSettings
from sim_service.world import World

GROUPED_NAMESPACE = "swimm/bench-grouped"
POLL_MS = 2.0  # the polling run's wait before sleeping, each side: longer than a round trip (about 1 ms)
ROUNDS = 8  # blocks per way of serving; each round measures the way and the in-process World once
#: Untimed steps each way (and the in-process world) takes first: a fresh process's first few hundred frames
#: are the slowest (Mesa compiles its shaders, caches fill; docs/benchmarks.md).
WARMUP_STEPS = 200
DEFAULT_SWITCH_INTERVAL_S = sys.getswitchinterval()  # what a blocking link runs with
#: How long a way's learner process may take: a start-up allowance, and 50 ms a step (some twenty times a
#: served step's round trip on a slow host).
LEARNER_START_S, LEARNER_S_PER_STEP = 120.0, 0.05
SCENERY_EPISODE_STEPS = 100  # the scenery measurement's episode length: 20 scenes a world in 2000 steps
SHARED_RENDERER_ENVS = 4  # the renderer measurement's group: a sim's share of 8 envs on two sims
ANTI_ALIASED_SCALE = 2  # the render-scale measurement's: frames drawn at 128x128 and area-downsampled to 64x64


@dataclass(frozen=True)
class Way:
    """One way of serving the env: its name, key prefix in the result, Zenoh mode, poll time (ms) and setting."""

    name: str
    prefix: str
    mode: str
    poll_ms: float
    low_latency: bool = False

    @property
    def namespace(self) -> str:
        return f"swimm/bench-{self.name}"

    def zenoh_settings(self, endpoint: str) -> ZenohSettings:
        return ZenohSettings(mode=self.mode, connect=[endpoint], namespace=self.namespace, low_latency=self.low_latency)

    def flags(self, endpoint: str) -> list[str]:
        """The command-line flags that give a swimm process this way's Zenoh settings and poll time."""
        flags = ["--mode", self.mode, "--connect", endpoint, "--namespace", self.namespace]
        return [*flags, *zenoh_flags(self.low_latency), "--poll-ms", str(self.poll_ms)]


#: The headline way first, as in the result.
WAYS = (
    Way("polling", "", "peer", POLL_MS, low_latency=True),
    Way("standard", "standard_", "peer", POLL_MS),
    Way("blocking", "blocking_", "peer", 0.0),
    Way("routed", "routed_", "client", 0.0),
)
WAYS_BY_NAME = {way.name: way for way in WAYS}


def random_actions(steps: int, seed: int = 0) -> list[tuple[float, float, float, float]]:
    rng = np.random.default_rng(seed)
    return [tuple(float(x) for x in row) for row in rng.uniform(-1, 1, (steps, 4))]


@dataclass
class Tally:
    """Steps and seconds summed over the blocks of one way, with every round trip."""

    steps: int = 0
    seconds: float = 0.0
    round_trips: list[float] = field(default_factory=list)

    @property
    def rate(self) -> float:
        return self.steps / self.seconds


def step_inprocess(world: World, actions: list, tally: Tally) -> None:
    """One World in this process takes ``actions`` back to back."""
    step_round_robin([world], actions, tally)


def step_round_robin(worlds: list[World], actions: list, tally: Tally) -> None:
    """Every world takes each action of ``actions`` in turn, as a sim steps its envs; counts env steps."""
    start = time.perf_counter()
    for action in actions:
        for world in worlds:
            world.step(action)
    tally.seconds += time.perf_counter() - start
    tally.steps += len(actions) * len(worlds)


class ServedEnv:
    """One env of a `swimm sim` process, claimed and reset, stepped lock-step from this process."""

    def __init__(self, way: Way, endpoint: str, stack: ExitStack) -> None:
        self.way = way
        settings = way.zenoh_settings(endpoint)
        session = stack.enter_context(open_session(settings, role="bench"))
        keys = Keys(settings.namespace)
        holder = new_holder_id("learner")
        stack.enter_context(announce(session, keys, "learner", holder))
        sims = stack.enter_context(Roster(session, keys, "sim"))
        sims.wait_for(1, timeout_s=60)
        self.link = EnvLink(session, keys, "train", ["0"], holder, encoded=False, poll_ms=way.poll_ms)
        stack.callback(self.link.close)
        self.link.claim()
        self.link.send_reset(1, 1)
        self.link.wait()

    def step(self, actions: list, tally: Tally) -> None:
        with switch_interval(POLLING_SWITCH_INTERVAL_S if self.way.poll_ms > 0 else DEFAULT_SWITCH_INTERVAL_S):
            start = time.perf_counter()
            for action in actions:
                sent = time.perf_counter()
                self.link.send([action])
                self.link.wait()
                tally.round_trips.append(time.perf_counter() - sent)
            tally.seconds += time.perf_counter() - start
        tally.steps += len(actions)


class GroupedEnvs:
    """``envs`` envs of the sims at ``endpoint``, each claimed and reset once, stepped in groups (blocking peers,
    Zenoh's defaults, as `swimm up` runs): every group's actions go out before the first reply is awaited."""

    def __init__(self, endpoint: str, envs: int, group_size: int, stack: ExitStack) -> None:
        settings = ZenohSettings(mode="peer", connect=[endpoint], namespace=GROUPED_NAMESPACE)
        session = stack.enter_context(open_session(settings, role="bench"))
        keys = Keys(settings.namespace)
        holder = new_holder_id("learner")
        stack.enter_context(announce(session, keys, "learner", holder))
        size = group_size or 1
        self.groups = []
        for start in range(0, envs, size):
            ids = [str(env) for env in range(start, min(start + size, envs))]
            group = EnvLink(session, keys, "train", ids, holder, encoded=False, group=f"{holder}.{start // size}")
            stack.callback(group.close)
            for index in range(len(ids)):
                group.claim(timeout_s=60, index=index)
                group.send_reset(1, 1 + start + index, index=index)
                group.wait()
            self.groups.append(group)
        self.envs = envs

    def step(self, actions: list, tally: Tally) -> None:
        """Each action of ``actions`` for every env at once (one vector step each); counts env steps."""
        start = time.perf_counter()
        for action in actions:
            sent = time.perf_counter()
            for group in self.groups:
                group.send([action] * len(group.envs))
            for group in self.groups:
                group.wait()
            tally.round_trips.append(time.perf_counter() - sent)
        tally.seconds += time.perf_counter() - start
        tally.steps += len(actions) * self.envs


def measure_groups(endpoint: str, envs: int, group_size: int, steps: int, rounds: int) -> dict[str, Tally]:
    """``steps`` env steps in-process (one World, the serial loop) and through the sims (``envs`` envs in groups),
    in ``rounds`` alternating blocks."""
    actions = random_actions(max(1, steps // envs))
    with ExitStack() as stack:
        world = warm_world(stack)
        served = GroupedEnvs(endpoint, envs, group_size, stack)
        served.step(random_actions(max(1, WARMUP_STEPS // envs), seed=1), Tally())
        # As many env steps in-process: every vector step's action once for each env, one World after the other.
        return alternate(world, served.step, actions, rounds, lambda block: [a for a in block for _ in range(envs)])


def warm_world(stack: ExitStack) -> World:
    """The in-process World, reset and past its slow first frames (:data:`WARMUP_STEPS`)."""
    world = World()
    stack.callback(world.close)
    world.reset(1)
    step_inprocess(world, random_actions(WARMUP_STEPS, seed=1), Tally())
    return world


def alternate(
    world: World, served_step: Callable[[list, Tally], None], actions: list, rounds: int,
    inprocess_actions: Callable[[list], list] = lambda block: block,
) -> dict[str, Tally]:  # fmt: skip
    """``actions`` in ``rounds`` blocks, each block served and (as ``inprocess_actions`` of it) in-process, which
    of the two goes first alternating from round to round."""
    tallies = {"inprocess": Tally(), "served": Tally()}
    for index, block in enumerate(np.array_split(np.arange(len(actions)), rounds)):
        block_actions = [actions[i] for i in block]
        for name in sorted(tallies, reverse=index % 2 == 1):
            if name == "served":
                served_step(block_actions, tallies[name])
            else:
                step_inprocess(world, inprocess_actions(block_actions), tallies[name])
    return tallies


@contextmanager
def switch_interval(seconds: float) -> Iterator[None]:
    """Run a block with the GIL switch interval its way of serving uses: a polling process runs with the one its
    entry point sets (services/process.py), a blocking one with Python's."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def measure_way(way: Way, endpoint: str, steps: int, rounds: int) -> dict[str, Tally]:
    """The learner's half, in its own process: ``steps`` in-process and through the sim, in ``rounds`` blocks
    each, alternating which of the two goes first."""
    with ExitStack() as stack:
        world = warm_world(stack)
        served = ServedEnv(way, endpoint, stack)
        served.step(random_actions(WARMUP_STEPS, seed=1), Tally())
        return alternate(world, served.step, random_actions(steps), rounds)


def run_learner(way: Way, endpoint: str, steps: int, rounds: int, sim: Service) -> dict[str, Tally]:
    """:func:`measure_way` in a learner process of its own (`python -m bench.sim`), stepping ``sim``."""
    command = [sys.executable, "-m", "bench.sim", way.name, endpoint, str(steps), str(rounds)]
    timeout_s = LEARNER_START_S + LEARNER_S_PER_STEP * (steps + WARMUP_STEPS)
    done = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, env=child_environment())
    if done.returncode != 0:
        raise RuntimeError(f"the {way.name} learner failed:\n{done.stderr[-3000:]}\nits sim's log:\n{sim.log_tail()}")
    return {name: Tally(**fields) for name, fields in json.loads(done.stdout).items()}


def measure_scenery(steps: int) -> dict:
    """In-process steps/s of the plain and the varied world, ``steps`` each, episode for episode in turn (which of
    the two goes first alternating), so both see the same drift of the machine's speed."""
    with ExitStack() as stack:
        worlds = {name: [World(WorldSettings(scene=SceneSettings(preset=name)))] for name in ("plain", "varied")}
        plain, varied = alternate_groups(worlds, steps, stack)
    return {
        "plain_steps_per_s": round(plain, 1),
        "varied_steps_per_s": round(varied, 1),
        "varied_over_plain": round(varied / plain, 3),
    }


def measure_render_scale(steps: int, scale: int = ANTI_ALIASED_SCALE) -> dict:
    """In-process steps/s of the plain world drawn as always and drawn anti-aliased (``scale`` times larger, then
    area-downsampled: ``WorldSettings.render_scale``), ``steps`` each, episode for episode in turn."""
    with ExitStack() as stack:
        worlds = {"point": [World()], "scaled": [World(WorldSettings(render_scale=scale))]}
        point, scaled = alternate_groups(worlds, steps, stack)
    return {
        "render_scale": scale,
        "render_point_steps_per_s": round(point, 1),
        "render_scaled_steps_per_s": round(scaled, 1),
        "render_scaled_over_point": round(scaled / point, 3),
    }


def measure_renderers(steps: int, envs: int = SHARED_RENDERER_ENVS) -> dict:
    """In-process steps/s of a sim's group of ``envs`` Worlds stepped one after another, each with a renderer of its
    own and all sharing one (one GL context, as `swimm sim` builds them), ``steps`` env steps each, in turn."""
    with ExitStack() as stack:
        own = [World() for _ in range(envs)]
        shared = [World()]
        shared += [World(share_renderer_with=shared[0]) for _ in range(envs - 1)]
        own_rate, shared_rate = alternate_groups({"own": own, "shared": shared}, steps, stack)
    return {
        "renderer_group_envs": envs,
        "own_renderers_steps_per_s": round(own_rate, 1),
        "shared_renderer_steps_per_s": round(shared_rate, 1),
        "shared_over_own_renderers": round(shared_rate / own_rate, 3),
    }


def alternate_groups(groups: dict[str, list[World]], steps: int, stack: ExitStack) -> list[float]:
    """Each group's env steps/s over ``steps`` env steps: episodes of :data:`SCENERY_EPISODE_STEPS` steps, one group
    after the other (which goes first alternating, so all see the same drift of the machine's speed), the worlds
    of a group stepped round-robin as a sim steps its envs."""
    tallies = {name: Tally() for name in groups}
    for world in (world for group in groups.values() for world in group):
        stack.callback(world.close)
        world.reset(0)
        step_inprocess(world, random_actions(WARMUP_STEPS, seed=1), Tally())
    for episode, block in enumerate(np.array_split(np.arange(steps), max(1, steps // SCENERY_EPISODE_STEPS))):
        for name in sorted(groups, reverse=episode % 2 == 1):
            group = groups[name]
            for index, world in enumerate(group):
                world.reset(episode * len(group) + index)
            step_round_robin(group, random_actions(len(block) // len(group), episode), tallies[name])
    return [tallies[name].rate for name in groups]


def run(steps: int = 2000, rounds: int = ROUNDS, envs: int = 1) -> dict:
    """``steps`` per way, taken in ``rounds`` blocks, and as many in-process steps alternating with them; with
    ``envs`` > 1, also ``steps`` env steps of that many envs in groups (the ``grouped_*`` keys). First the
    scenery's cost: ``steps`` in-process steps of the plain world and of the varied one."""
    if envs < 1:
        raise ValueError(f"--envs must be at least 1, got {envs}")
    result = measure_scenery(steps) | measure_render_scale(steps) | measure_renderers(steps)
    with tempfile.TemporaryDirectory(prefix="swimm-bench-") as tmp, ProcessGroup(Path(tmp)) as group:
        endpoint = group.start_router()
        for way in WAYS:
            sim = group.start(f"sim-{way.name}", "sim", *way.flags(endpoint), "--eval-envs", "0")
            tallies = run_learner(way, endpoint, steps, rounds, sim)
            group.stop(sim)
            result |= way_result(way, tallies["inprocess"], tallies["served"])
        if envs > 1:
            result |= grouped_result(group, endpoint, envs, steps, rounds)
    return result | {
        "topology": "peer",
        "transport": "low-latency" if WAYS[0].low_latency else "standard",
        "poll_ms": POLL_MS,
        "steps": steps,
        "rounds": rounds,
    }


def grouped_result(group: ProcessGroup, endpoint: str, envs: int, steps: int, rounds: int) -> dict:
    """The ``grouped_*`` keys: ``envs`` envs on the sims of :func:`bench.layout.default_layout`, in groups."""
    sims, group_size = default_layout(envs)
    started = []
    for index, (first, count) in enumerate(sim_shares(envs, sims)):
        started.append(group.start(f"sim-grouped-{index}", "sim", "--mode", "peer", "--connect", endpoint,
                                   "--namespace", GROUPED_NAMESPACE, "--train-envs", str(count),
                                   "--first-train-env", str(first), "--eval-envs", "0"))  # fmt: skip
    tallies = measure_groups(endpoint, envs, group_size, steps, rounds)
    for sim in started:
        group.stop(sim)
    inprocess, served = tallies["inprocess"], tallies["served"]
    return {
        "envs": envs,
        "grouped_sims": sims,
        "grouped_group_size": group_size,
        "grouped_inprocess_steps_per_s": round(inprocess.rate, 1),
        "grouped_steps_per_s": round(served.rate, 1),
        "grouped_ratio": round(served.rate / inprocess.rate, 3),
        "grouped_vector_step_p50_ms": percentile_ms(np.array(served.round_trips), 50),
    }


def way_result(way: Way, inprocess: Tally, served: Tally) -> dict:
    """A way's keys: its rate, its ratio to the in-process blocks it alternated with, and their rate."""
    round_trips = np.array(served.round_trips)
    return {
        f"{way.prefix}inprocess_steps_per_s": round(inprocess.rate, 1),
        f"{way.prefix or 'distributed_'}steps_per_s": round(served.rate, 1),
        f"{way.prefix}ratio": round(served.rate / inprocess.rate, 3),
        f"{way.prefix}p50_ms": percentile_ms(round_trips, 50),
        f"{way.prefix}p99_ms": percentile_ms(round_trips, 99),
    }


def percentile_ms(seconds: np.ndarray, q: float) -> float:
    return round(float(np.percentile(seconds, q)) * 1e3, 3)


def main(argv: list[str] | None = None) -> None:
    """The learner process of one way: prints its tallies as one JSON object."""
    parser = argparse.ArgumentParser(description="one way's learner process of `swimm bench sim`")
    parser.add_argument("way", choices=sorted(WAYS_BY_NAME))
    parser.add_argument("endpoint")
    parser.add_argument("steps", type=int)
    parser.add_argument("rounds", type=int)
    args = parser.parse_args(argv)
    # An entry point of its own: Zenoh's threads and Mesa's as a swimm process's defaults. The switch interval is
    # not set here: switch_interval gives each way's steps the one its link runs with.
    configure_process(
        ProcessSettings(zenoh_threads=ZenohSettings().zenoh_threads, render_threads=DEFAULT_RENDER_THREADS),
        role="bench learner",
    )
    tallies = measure_way(WAYS_BY_NAME[args.way], args.endpoint, args.steps, args.rounds)
    sys.stdout.write(json.dumps({name: vars(tally) for name, tally in tallies.items()}) + "\n")


if __name__ == "__main__":
    main()
