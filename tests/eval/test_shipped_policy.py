"""The policy to fly (learner_service/models/sac_cmvae_fans.zip, SHIPPED_POLICY) still tracks: a bare `swimm eval`'s
contender, on the real world with the CMVAE it records in one process, against the scripted baseline on the same
episode.

A short episode, so it guards the artefacts (a policy and an encoder that no longer fit each other, an
observation layout that changed under them) rather than measuring them; docs/eval_report.md measures. Its bounds
are loose, so the last test tells the shipped policies apart: each one's actions on fixed observations, measured once,
are checked tightly enough that swapping any other shipped policy in fails.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from eval_service.engine import EvaluationSettings, evaluate
from learner_service.export import SHIPPED_POLICY
from learner_service.identity import TRAINED_ON_KEY, read_identity
from learner_service.registry import load_policy
from services.results import REPO_ROOT, file_sha256
from tests.fingerprints import check_pairing

STEPS = 400


def test_the_shipped_policy_follows_the_dolphin_from_the_camera_alone(tmp_path) -> None:
    given = EvaluationSettings(backend="inprocess", obs="cmvae", algo=["scripted", "sac"], episodes=1, steps=STEPS,
                               seed=113, progress_bar=False, figures=False)  # fmt: skip
    summaries = evaluate(given, tmp_path)
    shipped, baseline = summaries["sac"], summaries["scripted"]
    assert shipped["A'"] == shipped["D'"] == shipped["C'"] == 0.0  # kept it in view, in the band, no contact
    assert shipped["mean_return"] > 0.6 * STEPS
    assert shipped["mean_return"] > 0.7 * baseline["mean_return"]


@pytest.mark.parametrize(("name", "noise"), [("sac_cmvae_3d.zip", "off"), ("sac_cmvae_3d_robust.zip", "murky")])
def test_the_shipped_3d_policies_follow_the_dolphin_in_depth_from_the_camera_alone(tmp_path, name, noise) -> None:
    """Each 3d policy on the vertical CMVAE it records, in the 3d task (the noise-robust one under the murky
    preset), against the ground-truth tracker on the same episode."""
    policy = Path(SHIPPED_POLICY).with_name(name)
    given = EvaluationSettings(backend="inprocess", obs="cmvae", task="3d", algo=["scripted", "sac"],
                               checkpoint=[str(policy)], noise=noise, episodes=1, steps=STEPS, seed=113,
                               progress_bar=False, figures=False)  # fmt: skip
    summaries = evaluate(given, tmp_path)
    shipped, baseline = summaries["sac"], summaries["scripted"]
    assert shipped["A'"] == shipped["D'"] == shipped["C'"] == 0.0
    assert shipped["E"] < 0.2  # it heaves: with depth held the dolphin's elevation error is about 0.34
    assert shipped["mean_return"] > 0.7 * baseline["mean_return"]


#: The shipped policies, each told apart from every other by its actions on IDENTITY_OBS fixed observations: latents
#: and action history drawn uniformly from [-1, 1] with IDENTITY_SEED (the layout each policy reads: 30 numbers, 40 for
#: the 3d policies' 10 previous (surge, heave, yaw) actions).
SHIPPED = (
    "sac_cmvae.zip",
    "sac_cmvae_robust.zip",
    "sac_cmvae_latency.zip",
    "sac_cmvae_fly.zip",
    "sac_cmvae_general.zip",
    "sac_cmvae_wide.zip",
    "sac_cmvae_3d.zip",
    "sac_cmvae_3d_robust.zip",
    "sac_pod_detector.zip",
)
IDENTITY_OBS, IDENTITY_SEED = 8, 0
#: Each shipped policy's deterministic actions (surge, yaw; the 3d ones' surge, heave, yaw) on those observations,
#: measured at commit 9eb0b59 (sac_cmvae_wide.zip, the 3d ones and sac_pod_detector.zip at the commits that added or
#: replaced them) by `PYTHONPATH=. python tests/eval/test_shipped_policy.py`, which prints this table. A planar
#: policy's actions never match a 3d one's record: their shapes differ.
ACTIONS = {
    "sac_cmvae.zip": [[0.2307, -0.3087], [-0.6881, -0.0515], [-0.0101, -0.3469], [0.3981, 0.6308],
                      [-0.5726, -0.259], [-0.7854, 0.172], [-0.5268, -0.4261], [-0.964, -0.1179]],
    "sac_cmvae_robust.zip": [[0.6542, -0.1147], [0.9396, -0.0789], [-0.5964, -0.3497], [0.964, 0.6964],
                             [-0.2789, -0.2549], [-0.964, -0.1779], [0.964, -0.2797], [-0.964, -0.1747]],
    "sac_cmvae_latency.zip": [[0.5574, 0.5631], [0.9446, 0.1711], [-0.7007, -0.5551], [0.964, 0.6973],
                              [-0.5018, -0.5005], [-0.964, -0.4814], [0.964, -0.1222], [-0.964, -0.248]],
    "sac_cmvae_fly.zip": [[0.7633, 0.4777], [0.9158, 0.2701], [-0.5104, -0.5719], [0.964, 0.7364],
                          [-0.3999, -0.4222], [-0.964, -0.3703], [0.964, -0.1276], [-0.964, -0.1508]],
    "sac_cmvae_general.zip": [[0.7351, 0.5838], [0.964, 0.1851], [-0.6207, -0.5416], [0.964, 0.6368],
                              [-0.5261, -0.5585], [-0.964, -0.5027], [0.964, -0.1226], [-0.964, -0.2073]],
    "sac_cmvae_wide.zip": [[0.6874, 0.1931], [0.964, 0.1463], [-0.7298, -0.6982], [0.964, 0.3201],
                           [-0.6142, -0.3148], [-0.964, -0.4199], [0.964, 0.0012], [-0.964, 0.0001]],
    "sac_cmvae_3d.zip": [[0.1439, 0.964, -0.0332], [0.0692, 0.5812, -0.0991], [0.575, -0.9193, 0.1028],
                         [-0.2547, -0.7622, -0.0281], [-0.3398, -0.964, 0.0033], [-0.3235, 0.9368, -0.09],
                         [-0.6453, 0.235, 0.4251], [-0.0402, 0.2359, 0.3064]],
    "sac_cmvae_3d_robust.zip": [[0.1094, 0.964, -0.0787], [-0.0, 0.7383, -0.0388], [0.5478, -0.929, 0.0919],
                                [-0.3043, -0.466, 0.0574], [-0.2529, -0.964, -0.0549], [-0.2948, 0.9249, -0.0641],
                                [-0.6505, 0.3871, 0.339], [-0.15, 0.2575, 0.3028]],
    "sac_pod_detector.zip": [[0.8503, 0.1198], [0.964, 0.1948], [-0.7849, -0.6855], [0.964, 0.5458],
                             [-0.808, -0.3528], [-0.964, -0.5044], [0.964, -0.0266], [-0.964, 0.0008]],
}  # fmt: skip
#: Room for a float library that differs in the last bits; any two shipped policies of one task differ by at least
#: 0.13 on some action, six times this.
ACTION_TOLERANCE = 0.02


def _actions(checkpoint: Path) -> np.ndarray:
    """The policy's deterministic actions on the fixed observations, (IDENTITY_OBS, its action size)."""
    policy = load_policy("sac", checkpoint, device="cpu")
    shape = policy.model.observation_space.shape
    obs = np.random.default_rng(IDENTITY_SEED).uniform(-1.0, 1.0, size=(IDENTITY_OBS, *shape)).astype(np.float32)
    return policy.act(obs, {}).astype(np.float64)


@pytest.fixture(scope="module")
def shipped_actions() -> dict[str, np.ndarray]:
    models = SHIPPED_POLICY.parent
    return {name: _actions(models / name) for name in SHIPPED}


@pytest.mark.parametrize("candidate", SHIPPED)
@pytest.mark.parametrize("expected", SHIPPED)
def test_a_shipped_policy_takes_its_measured_actions_and_no_other_shipped_policy_does(
    shipped_actions: dict[str, np.ndarray], expected: str, candidate: str
) -> None:
    check_pairing(shipped_actions, ACTIONS, ACTION_TOLERANCE, candidate, expected)


def test_the_policy_to_fly_is_sac_cmvae_wide_rebound_to_its_fine_tuned_cmvae(shipped_actions) -> None:
    """Not a policy of its own: sac_cmvae_wide.zip's weights, recording cmvae_fans.pt as the CMVAE it flies on and
    cmvae_wide.pt as the one it trained on (`swimm rebind`; docs/learner.md, "One policy to fly")."""
    np.testing.assert_array_equal(_actions(SHIPPED_POLICY), shipped_actions["sac_cmvae_wide.zip"])
    identity, encoders = read_identity(SHIPPED_POLICY), REPO_ROOT / "encoder_service" / "models"
    assert identity["encoder"]["sha256"] == file_sha256(encoders / "cmvae_fans.pt")
    assert identity[TRAINED_ON_KEY]["sha256"] == file_sha256(encoders / "cmvae_wide.pt")


if __name__ == "__main__":  # measures ACTIONS on the checked-out policies
    for shipped in SHIPPED:
        print(f"{shipped!r}: {np.round(_actions(SHIPPED_POLICY.parent / shipped), 4).tolist()},")
