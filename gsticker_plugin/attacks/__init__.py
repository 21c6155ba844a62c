"""Image distortions ("attacks") for robustness training and evaluation of the message extractor.

All functions take float RGB images ``Float[Tensor, "B 3 H W"]`` in [0, 1] and return a new image of the same
shape, dtype and device, clamped to [0, 1] (``gaussian_blur``, ``resize`` and ``rotate`` take ``clamp=False``
for their unclamped, linear-in-the-image form, which the image decoder applies to small changes). They are differentiable wherever the operation allows (they sit
between the renderer and the extractor during training), and every random one takes an optional
``generator: torch.Generator | None`` (random numbers are drawn on the generator's device and moved to the
image's device, so a CPU generator gives the same draws for CPU and CUDA images).

Split by family (videoseal style): ``geometric`` (rotate, cropout, resize) and ``valuemetric`` (noise, blur, hue,
JPEG), each a function with its thin ``nn.Module`` (kornia style); ``spec`` holds :data:`ATTACKS`,
:func:`parse_attack_spec` and :func:`apply_attacks` (the ``name=strength`` interface of the CLIs); ``training`` the
training-time :class:`RandomDistortion`. The evaluation grids are data: the protocol YAMLs in method_configs/eval/.

Strengths may be a Python number (one for the batch) or, for every attack, a per-image tensor ``[B]``.
Python numbers are range-checked (``ValueError``); tensors are trusted, since checking them would force a
device sync in the training loop.

float16/bfloat16 images are processed in float32 and rounded back once at the end.
"""

from gsticker_plugin.attacks.common import Strength
from gsticker_plugin.attacks.geometric import Cropout, Resize, Rotate, cropout, resize, rotate
from gsticker_plugin.attacks.spec import (
    ATTACK_NAMES,
    ATTACKS,
    AttackFn,
    apply_attacks,
    check_strength,
    parse_attack_spec,
)
from gsticker_plugin.attacks.training import RandomDistortion, RandomDistortionConfig
from gsticker_plugin.attacks.valuemetric import (
    JPEG,
    GaussianBlur,
    GaussianNoise,
    HueShift,
    blur_kernel_size,
    gaussian_blur,
    gaussian_noise,
    hue_shift,
    jpeg,
)

__all__ = [
    "ATTACKS",
    "ATTACK_NAMES",
    "AttackFn",
    "Cropout",
    "GaussianBlur",
    "GaussianNoise",
    "HueShift",
    "JPEG",
    "RandomDistortion",
    "RandomDistortionConfig",
    "Resize",
    "Rotate",
    "Strength",
    "apply_attacks",
    "blur_kernel_size",
    "check_strength",
    "cropout",
    "gaussian_blur",
    "gaussian_noise",
    "hue_shift",
    "jpeg",
    "parse_attack_spec",
    "resize",
    "rotate",
]
