"""Anti-aliased downsampling tried on the 3d CMVAE (scratch, not built): a binomial blur before every stride-2 step.

Patches ``encoder_service.model.ImageEncoder`` so each stride-2 convolution (the first, the residual blocks' and
their shortcuts') reads a [1 2 1] x [1 2 1] / 16 blurred input, and the max pool takes its maximum at stride 1 and
then blurs and subsamples (Zhang 2019, "Making convolutional networks shift-invariant again"). The blur holds no
weights, so a checkpoint's keys stay as they are and ``--init`` starts from the plain model. Then runs a `swimm`
command or a script with the patch in place (docs/learner.md, the 3d tries):

    MUJOCO_GL=egl python blur_pool.py swimm train-encoder --dataset data/vert \
        --init encoder_service/models/cmvae_vertical.pt ...
    MUJOCO_GL=egl python blur_pool.py run return_budget.py OUT.csv --tracker camera --checkpoint runs/blur-mirror.pt ...
"""

import runpy
import sys

import torch
import torch.nn.functional as F

import encoder_service.model as model

_ROW = torch.tensor([1.0, 2.0, 1.0])
_KERNEL = (_ROW[:, None] * _ROW[None, :]) / 16.0


def blur(x: torch.Tensor) -> torch.Tensor:
    channels = x.shape[1]
    weight = _KERNEL.to(x.dtype).expand(channels, 1, 3, 3)
    return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), weight, groups=channels)


def _blur_input(module, inputs):
    return (blur(inputs[0]),)


def _blur_and_subsample(module, inputs, output):
    return blur(output)[:, :, ::2, ::2]


_plain_init = model.ImageEncoder.__init__


def _blurred_init(self, *args, **kwargs):
    _plain_init(self, *args, **kwargs)
    features = self.features
    features[0].register_forward_pre_hook(_blur_input)
    features[1].stride = 1
    features[1].register_forward_hook(_blur_and_subsample)
    for block in features[2:5]:
        block.branch[2].register_forward_pre_hook(_blur_input)
        block.shortcut.register_forward_pre_hook(_blur_input)


model.ImageEncoder.__init__ = _blurred_init

if __name__ == "__main__":
    what, *rest = sys.argv[1:]
    if what == "swimm":
        from swimm.cli import main

        sys.argv = ["swimm", *rest]
        sys.exit(main())
    sys.path.insert(0, ".")
    sys.argv = rest
    runpy.run_path(rest[0], run_name="__main__")
