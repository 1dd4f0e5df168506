"""Is a locating CMVAE's locator itself misled by the low sun's light shafts, or does its head ignore it?

For reset frames of the selection seed (211) in the clean world and in the low-sun split: how the locator's
soft-argmax column follows the true azimuth, and how often its side (left/right of centre) and the latent's theta
have the true azimuth's sign. Run from the repository root:

    MUJOCO_GL=egl python docs/encoder/selection/locator_diagnosis.py runs/locate/best.pt OUT.csv
"""

import sys

import numpy as np
import pandas as pd
import torch

from encoder_service.model import denormalise_labels, images_to_tensor, load_model, soft_argmax
from learner_service.task import episode_seed
from services.results import provenance, write_provenance_beside
from sim_service.dataset import labels_and_pose
from sim_service.settings import WorldSettings
from sim_service.splits import SPLITS
from sim_service.world import World

FRAMES = 150


def main(checkpoint: str, out: str) -> None:
    model, _ = load_model(checkpoint)
    reader = model.encoder.head[0].weight.detach()
    features = model.encoder.FEATURES
    print(
        f"reader column norms: pooled features {reader[:, :features].norm(dim=0).mean():.3f} on average, "
        f"soft-argmax column {reader[:, features].norm():.3f}, row {reader[:, features + 1].norm():.3f}"
    )
    world = World(WorldSettings())
    rows = []
    try:
        for name in ("clean", "low-sun"):
            split = SPLITS.get(name)
            frames, labels = [], []
            for frame in range(1, FRAMES + 1):
                noise = split.noise if split is not None and split.noise.enabled else False
                telemetry, image = world.reset(episode_seed(211, frame), noise=noise, scene=split and split.scene)
                frames.append(image)
                labels.append(labels_and_pose(telemetry)[0])
            true_theta = np.stack(labels)[:, 1]
            with torch.no_grad():
                mu, _, _, where = model.encoder.with_feature_map(images_to_tensor(np.stack(frames)))
                column = soft_argmax(where)[:, 0].numpy()
                theta = denormalise_labels(model.decode_state(mu).numpy(), model.labels)[:, 1]
            rows.append({"condition": name, "frames": FRAMES,
                         "corr_column_theta": float(np.corrcoef(column, true_theta)[0, 1]),
                         "locator_side_right": float(np.mean(np.sign(-column) == np.sign(true_theta))),
                         "latent_sign_right": float(np.mean(np.sign(theta) == np.sign(true_theta))),
                         "theta_mae_deg": float(np.abs(theta - true_theta).mean())})  # fmt: skip
    finally:
        world.close()
    table = pd.DataFrame(rows)
    table.to_csv(out, index=False)
    write_provenance_beside(out, provenance({"cmvae": checkpoint}, seeds=[211]))
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3g}"))


if __name__ == "__main__":
    main(*sys.argv[1:3])
