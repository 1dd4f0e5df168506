"""Along the camera-only tracker's 3d loop (stage i of cmvae_vertical.pt, surge gain 0.5), each step's observation
(the full latent and ActPrev), the true d, azimuth and elevation, and the CMVAE's reading, saved as one array for
latent_correction_fit.py (docs/learner.md, the 3d tries; scratch, not built):

    MUJOCO_GL=egl python latent_correction_collect.py SEED EPISODES OUT.npy     # run from the repository root
"""

import sys

import numpy as np

from encoder_service.inference import LatentEncoder
from learner_service.envs import make_env
from learner_service.learn_settings import TrackerGains
from learner_service.scripted import LatentTracker
from learner_service.task import TaskSettings

seed, episodes, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
encoder = LatentEncoder("encoder_service/models/cmvae_vertical.pt")
env = make_env("inprocess", TaskSettings(obs="cmvae", task="3d"), base_seed=seed, encoder=encoder)
tracker = LatentTracker(encoder.decode_state, encoder.n_z, TrackerGains(surge_gain=0.5))
rows = []
for episode in range(episodes):
    obs, info = env.reset()
    for step in range(3000):
        o = np.asarray(obs, np.float32)
        read = [float(v[0]) for v in encoder.decode_state(o[None, : encoder.n_z])]
        rows.append([episode, step, *o, info["d"], info["azimuth"], info["elevation"], *read])
        obs, _, terminated, truncated, info = env.step(tracker.act(obs, info))
        if terminated or truncated:
            break
    print("episode", episode, len(rows), flush=True)
np.save(out, np.array(rows, np.float64))
