"""The camera-only tracker on stage i with its d read corrected by an MLP on the observation, fitted to the d
read's error on latent_correction_collect.py's loop rows of seeds 211 and 212; ``plain`` leaves the read as it is
(scratch, not built; output latent-correction-loop.txt):

    MUJOCO_GL=egl python latent_correction_loop.py corrected 213 3 ROWS-211.npy ROWS-212.npy   # and plain
"""

import sys

import numpy as np
import torch

from encoder_service.inference import LatentEncoder
from learner_service.envs import make_env
from learner_service.learn_settings import TrackerGains
from learner_service.scripted import LatentTracker
from learner_service.task import TaskSettings, swimm2_elevation_penalty, swimm2_penalties

torch.manual_seed(0)
np.random.seed(0)
torch.set_num_threads(1)
mode, seed, episodes, row_files = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4:]
rows = np.concatenate([np.load(p) for p in row_files])
n_obs = rows.shape[1] - 9
X = torch.tensor(rows[:, 2 : 2 + n_obs], dtype=torch.float32)
Y = torch.tensor(rows[:, 5 + n_obs] - rows[:, 2 + n_obs], dtype=torch.float32)[:, None]
mu, sd = X.mean(0), X.std(0) + 1e-6
net = torch.nn.Sequential(
    torch.nn.Linear(n_obs, 64), torch.nn.ReLU(), torch.nn.Linear(64, 64), torch.nn.ReLU(), torch.nn.Linear(64, 1)
)
opt = torch.optim.Adam(net.parameters(), 1e-3, weight_decay=1e-4)
for _ in range(3000):
    i = torch.randint(0, len(X), (256,))
    loss = (net((X[i] - mu) / sd) - Y[i]).abs().mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
encoder = LatentEncoder("encoder_service/models/cmvae_vertical.pt")
env = make_env("inprocess", TaskSettings(obs="cmvae", task="3d"), base_seed=seed, encoder=encoder)
tracker = LatentTracker(encoder.decode_state, encoder.n_z, TrackerGains(surge_gain=0.5))
for episode in range(episodes):
    obs, info = env.reset()
    pd_ = pt = pe = 0.0
    errs = []
    for _ in range(3000):
        o = np.asarray(obs, np.float32)
        d, theta, _, elevation = (float(v[0]) for v in encoder.decode_state(o[None, : encoder.n_z]))
        if mode == "corrected":
            with torch.no_grad():
                d -= float(net((torch.tensor(o)[None] - mu) / sd)[0, 0])
        errs.append(d - info["d"])
        a, b = swimm2_penalties(info["d"], abs(info["azimuth"]))
        pd_ += a
        pt += b
        pe += swimm2_elevation_penalty(abs(info["elevation"]))
        obs, _, terminated, truncated, info = env.step(tracker.command(d, theta, obs, elevation))
        if terminated or truncated:
            break
    steps = len(errs)
    print(
        f"{mode} seed {seed} ep {episode + 1}: return {steps - pd_ - pt - pe:.1f} distance {pd_:.1f} azimuth {pt:.1f}"
        f" elevation {pe:.1f} d err MAE {np.mean(np.abs(errs)):.3f} bias {np.mean(errs):.3f} steps {steps}",
        flush=True,
    )
