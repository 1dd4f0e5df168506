"""A distance readout from the whole latent: an MLP on stage i's mu, fitted to the true d of 32,768 frames of the
vertical training set (`swimm dataset --vertical --count 60000 --seed 3`, its first eight shards; the last 5,000
held out), then read on the camera tracker's loop rows of latent_correction_collect.py (scratch, not built;
output latent-correction-readout.txt):

    python latent_correction_readout.py DATASET rows-211.npy rows-212.npy      # run from the repository root
"""

import glob
import sys

import numpy as np
import torch

from encoder_service.inference import LatentEncoder

torch.manual_seed(0)
np.random.seed(0)
torch.set_num_threads(2)

enc = LatentEncoder("encoder_service/models/cmvae_vertical.pt", threads=2)
imgs, labs = [], []
for shard in sorted(glob.glob(f"{sys.argv[1]}/shard-*.images.npy"))[:8]:
    imgs.append(np.load(shard))
    labs.append(np.load(shard.replace("images", "labels")))
imgs, labs = np.concatenate(imgs), np.concatenate(labs)
mus = np.concatenate([enc.encode(imgs[i : i + 256])[0] for i in range(0, len(imgs), 256)])
read_d = enc.decode_state(mus)[0]
d = labs[:, 0]
n = len(d)
tr, va = slice(0, n - 5000), slice(n - 5000, n)
print(f"{n} frames; decoder d MAE on val {abs(read_d[va] - d[va]).mean():.3f}")
X = torch.tensor(mus, dtype=torch.float32)
Y = torch.tensor(d, dtype=torch.float32)[:, None]
net = torch.nn.Sequential(
    torch.nn.Linear(10, 64), torch.nn.ReLU(), torch.nn.Linear(64, 64), torch.nn.ReLU(), torch.nn.Linear(64, 1)
)
opt = torch.optim.Adam(net.parameters(), 1e-3)
idx = np.arange(n - 5000)
for _ in range(6000):
    i = torch.tensor(np.random.choice(idx, 256))
    loss = (net(X[i]) - Y[i]).abs().mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
with torch.no_grad():
    print(f"MLP d MAE on val {abs(net(X[va])[:, 0].numpy() - d[va]).mean():.3f}")
    for p in sys.argv[2:]:
        r = np.load(p)
        n_obs = r.shape[1] - 9
        mu = r[:, 2:12]
        true_d = r[:, 2 + n_obs]
        rd = r[:, 5 + n_obs]
        md = net(torch.tensor(mu, dtype=torch.float32))[:, 0].numpy()
        print(
            p,
            f"loop: decoder d MAE {abs(rd - true_d).mean():.3f} bias {(rd - true_d).mean():.3f};",
            f"MLP MAE {abs(md - true_d).mean():.3f} bias {(md - true_d).mean():.3f}",
        )
