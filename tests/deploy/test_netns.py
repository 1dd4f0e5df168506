"""Router, sim, two encoders and a learner on five "hosts" (network namespaces on one virtual LAN).

Each service runs in its own namespace with its own address and reaches the others only over its veth
cable to a bridge. Mid-run the cable of an encoder that serves some of the envs is pulled. The router
drops that encoder when its lease runs out, its liveliness token goes, the learner's retries re-route
those envs to the other encoder, and stepping goes on. The learner's log must then show every env's
steps exactly once and in order, and the sim's clock (sim_time / physics_dt) must equal the step
number, so no action was lost or applied twice.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import torch

from encoder_service.model import CMVAE, make_checkpoint
from services.presence import rendezvous_choice
from services.procs import ProcessGroup
from sim_service.settings import WorldSettings
from tests.deploy.netns import VirtualLan, netns_unavailable_reason
from tests.deploy.secure_zenoh import ZENOH_DIR

pytestmark = pytest.mark.slow
ENVS = 4
STEPS = 160
CUT_AFTER_STEPS = 30
ENCODERS = ("enc-a", "enc-b")


@pytest.fixture
def lan():
    reason = netns_unavailable_reason()
    if reason:
        pytest.skip(reason)
    lan = VirtualLan()
    try:
        yield lan
    finally:
        lan.close()


def read_log(path: Path) -> tuple[list[dict], dict | None]:
    lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.exists() else []
    replies = [line for line in lines if "summary" not in line]
    summaries = [line["summary"] for line in lines if "summary" in line]
    return replies, (summaries[0] if summaries else None)


@pytest.mark.parametrize("sites", [1, 2], ids=["one-router", "two-sites"])
def test_cutting_an_encoders_link_loses_and_repeats_no_step(lan, processes: ProcessGroup, namespace, tmp_path, sites):
    """``two-sites``: the encoders sit behind a second router (deploy/zenoh/router-site.json5) joined to the first,
    with deploy/zenoh/client-lan.json5's 3 s lease, as on a GPU box serving a sim elsewhere."""
    checkpoint = tmp_path / "cmvae.pt"
    torch.manual_seed(0)
    torch.save(make_checkpoint(CMVAE(n_z=10), beta=8.0, epoch=1, val_loss=1.0, metrics={}), checkpoint)
    routers = ["router-a", "router-b"][:sites]
    addresses = {host: lan.add_host(host) for host in (*routers, "sim", *ENCODERS, "learner")}
    endpoint = f"tcp/{addresses['router-a']}:7447"
    encoder_endpoint = f"tcp/{addresses[routers[-1]]}:7447"
    common = ["--connect", endpoint, "--namespace", namespace]

    lan.start(processes, "router-a", "router-a", ["-m", "swimm", "router", "--listen", endpoint])
    encoder_args = ["--connect", encoder_endpoint, "--namespace", namespace]
    if sites == 2:
        site_config = str(ZENOH_DIR / "router-site.json5")
        lan.start(
            processes, "router-b", "router-b",
            ["-m", "swimm", "router", "--zenoh-config", site_config, "--listen", encoder_endpoint,
             "--connect", endpoint],
        )  # fmt: skip
        encoder_args += ["--zenoh-config", str(ZENOH_DIR / "client-lan.json5")]
    lan.start(processes, "sim", "sim", ["-m", "swimm", "sim", *common, "--train-envs", str(ENVS)])
    for ident in ENCODERS:
        lan.start(
            processes, ident, ident,
            ["-m", "swimm", "encoder", *encoder_args, "--checkpoint", str(checkpoint), "--ident", ident,
             "--threads", "1"],
        )  # fmt: skip
    log_path = tmp_path / "replies.jsonl"
    driver = lan.start(
        processes, "learner", "learner",
        ["-m", "tests.deploy.lockstep_driver", *common, "--envs", str(ENVS), "--steps", str(STEPS),
         "--out", str(log_path)],
    )  # fmt: skip

    # The env ids whose frames the cut encoder encodes (the learner's own rendezvous choice).
    cut = rendezvous_choice("train/0", set(ENCODERS))
    moved = {str(i) for i in range(ENVS) if rendezvous_choice(f"train/{i}", set(ENCODERS)) == cut}
    deadline = time.monotonic() + 240
    while len(read_log(log_path)[0]) < ENVS * (CUT_AFTER_STEPS + 1):
        processes.check_alive()
        assert time.monotonic() < deadline, f"no progress before the cut:\n{driver.log_tail()}"
        time.sleep(0.2)
    lan.cut(cut)
    assert driver.process.wait(timeout=300) == 0, driver.log_tail()
    replies, summary = read_log(log_path)
    # An env whose step was in flight at the cut waited and re-sent; the others were simply routed elsewhere.
    assert sum(summary[env]["retries"] for env in moved) >= 1
    # The outage: the longest pause between two replies, from the cut to the moved envs stepping again.
    times = sorted(r["t"] for r in replies)
    outage_s = max(b - a for a, b in zip(times, times[1:], strict=False))
    lease_s = 3.0 if sites == 2 else 10.0  # client-lan.json5's lease, or Zenoh's default
    assert lease_s * 0.5 < outage_s < lease_s + 8.0, f"outage {outage_s:.1f} s with a {lease_s:.0f} s lease"

    dt = WorldSettings().physics_dt
    for env in (str(i) for i in range(ENVS)):
        steps = [r for r in replies if r["env"] == env]
        assert [(r["ep"], r["seq"]) for r in steps] == [(1, seq) for seq in range(STEPS + 1)]
        assert [round(r["sim_time"] / dt) for r in steps] == list(range(STEPS + 1))  # each action applied once
        encoders = summary[env]["encoders"]
        assert set(encoders) <= set(ENCODERS)  # every step's latent was seen, from a known encoder
        if env in moved:  # encoded by the cut encoder before the cut, by the other one after
            assert encoders[1] == cut and encoders[-1] != cut
        else:  # the envs of the encoder that stayed never moved
            assert set(encoders) == {encoders[-1]} != {cut}
