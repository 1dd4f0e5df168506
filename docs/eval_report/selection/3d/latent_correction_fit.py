"""Can the rest of the latent, earlier latents or the actions predict the CMVAE's read error in the 3d loop?

Fits the error (read minus true: metres for d, degrees for the angles) of d, theta and the elevation on each
step's observation, with 0, 3 or 8 earlier latents beside it, linearly and with a small MLP, on the steps of one
seed's episodes, and reports the corrected read's MAE on another seed's (files from latent_correction_collect.py;
output latent-correction.txt):

    python latent_correction_fit.py rows-211.npy rows-212.npy
"""

import sys

import numpy as np
import torch

torch.manual_seed(0)


def load(path):
    r = np.load(path)
    ep, step = r[:, 0], r[:, 1]
    n_obs = r.shape[1] - 2 - 3 - 4
    obs = r[:, 2 : 2 + n_obs]
    d, az, el = r[:, 2 + n_obs : 5 + n_obs].T
    read = r[:, 5 + n_obs :]
    return ep, step, obs, az, el, read, d


def features(ep, obs, lags):
    feats = [obs]
    for k in range(1, lags + 1):
        lagged = np.roll(obs[:, :10], k, axis=0)
        same = np.roll(ep, k) == ep
        lagged[~same] = obs[~same, :10]
        feats.append(lagged)
    return np.concatenate(feats, 1)


tr, te = load(sys.argv[1]), load(sys.argv[2])
for name, idx, truth in (("d", 0, 6), ("theta", 1, 3), ("elevation", 3, 4)):
    ytr = tr[5][:, idx] - tr[truth]
    yte = te[5][:, idx] - te[truth]
    print(
        f"{name}: raw read MAE train {abs(ytr).mean():.3f} test {abs(yte).mean():.3f};"
        f" bias-only test {abs(yte - ytr.mean()).mean():.3f}"
    )
    for lags in (0, 3, 8):
        Xtr, Xte = features(tr[0], tr[2], lags), features(te[0], te[2], lags)
        mu, sd = Xtr.mean(0), Xtr.std(0) + 1e-6
        Xtr, Xte = (Xtr - mu) / sd, (Xte - mu) / sd
        A = np.c_[Xtr, np.ones(len(Xtr))]
        w = np.linalg.lstsq(A, ytr, rcond=None)[0]
        lin = abs(yte - np.c_[Xte, np.ones(len(Xte))] @ w).mean()
        net = torch.nn.Sequential(
            torch.nn.Linear(Xtr.shape[1], 64),
            torch.nn.ReLU(),
            torch.nn.Linear(64, 64),
            torch.nn.ReLU(),
            torch.nn.Linear(64, 1),
        )
        opt = torch.optim.Adam(net.parameters(), 1e-3, weight_decay=1e-4)
        X, Y = torch.tensor(Xtr, dtype=torch.float32), torch.tensor(ytr, dtype=torch.float32)[:, None]
        for _ in range(3000):
            i = torch.randint(0, len(X), (256,))
            loss = (net(X[i]) - Y[i]).abs().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            mlp = abs(yte - net(torch.tensor(Xte, dtype=torch.float32))[:, 0].numpy()).mean()
        print(f"  lags {lags}: linear corrected MAE {lin:.3f}, MLP {mlp:.3f}")
