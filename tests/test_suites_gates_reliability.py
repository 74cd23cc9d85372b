"""Issue 47, third round: suites and gates under hostile state files and extreme numbers.

One class per fault class (RELIABILITY.md):

- TestStateFilesAreData: suite.json, the suite manifest, result.json and job records are
  read as data: every identifier re-checked by the validator the suite file goes through
  (orchestrate.suite.folder_name), every path the one its writer makes, the suite's sha256
  recomputed from its definition and checked against the folder's marker and manifest (and
  each entry against its dataset's config.json). A malformed or rewritten file is one line,
  exit 2, and nothing outside the suite folder's own report outputs changes.
- TestDerivedNumbersAreFinite: `check --calibrate` computes Student's upper-tail quantile
  directly (an independent 50-digit oracle checks it); 1e-300 gives finite bounds; what
  leaves float range is one line; a NaN or infinite metric in `check` is exit 2, not 1.
- TestUserStringsAreText: names are drawn as text in every figure (eval.report.plain_text);
  a report that fails leaves no earlier report looking current; NUL or '/' in a suite id
  is one line.
- TestGatesCompareLikeWithLike: `check` and `check --calibrate` refuse other or mixed
  scoring protocols, naming them; calibrated files record theirs; an older file is ours.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tomllib
from pathlib import Path

import pytest
from suite_toml import suite_toml
from test_suite import one_line_error, run

from nerfgauge.cli import main
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import json_bytes, read_json, write_json

TINY_DATASET = {"width": 16, "height": 16, "views": 4, "val_views": 0, "test_views": 2, "spp": 2}
OWN_OUTPUTS = ("leaderboard.json", "leaderboard.md", "leaderboard.html", "robustness.png", ".nerfgauge.lock")


def snapshot(root: Path) -> dict:
    """{relative path: (size, mtime_ns)} of every file under root (links not followed)."""
    found = {}
    for parent, _, names in os.walk(root):
        for name in names:
            path = Path(parent) / name
            info = path.lstat()
            found[path.relative_to(root).as_posix()] = (info.st_size, info.st_mtime_ns)
    return found


def report_output(rel: str) -> bool:
    """What `suite report` owns in a suite folder: it removes and rewrites these."""
    return rel in OWN_OUTPUTS or rel.startswith("report/")


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """A finished `suite run` of two 16x16 datasets (10 steps of our NeRF, the nearest baseline)."""
    root = tmp_path_factory.mktemp("ran")
    toml = root / "tiny.toml"
    toml.write_text(suite_toml("tiny", TINY_DATASET, {"steps": 10}))
    assert main(["suite", "run", str(toml), "--out", str(root / "S")]) == 0
    return toml, root / "S"


@pytest.fixture
def suite_copy(ran, tmp_path):
    """A copy of the finished suite folder (mtimes kept) and its .toml."""
    toml, folder = ran
    copy = tmp_path / "S"
    shutil.copytree(folder, copy, symlinks=True)
    return toml, copy


def rewrite_everywhere(folder: Path, edit) -> str:
    """A thorough forger: edit suite.json's definition, then recompute its sha256 and write it
    into suite.json, the suite manifest, every result.json and the folder's marker. Returns it."""
    recorded = read_json(folder / "suite.json")
    edit(recorded["definition"])
    sha = hashlib.sha256(json_bytes(recorded["definition"])).hexdigest()
    recorded["suite_sha256"] = sha
    write_json(folder / "suite.json", recorded)
    for path in [folder / "suite-manifest.json", *folder.glob("results/*/result.json")]:
        document = read_json(path)
        document["suite_sha256"] = sha
        write_json(path, document)
    marker = read_json(folder / ".nerfgauge.json")
    marker["recipe"] = sha
    write_json(folder / ".nerfgauge.json", marker)
    return sha


def rename_entry(document: dict, old: str, new: str) -> None:
    document[new] = document.pop(old)


class TestStateFilesAreData:
    @pytest.mark.slow
    def test_the_issues_example_ids_leading_out_with_every_hash_recomputed(self, suite_copy, capsys):
        """The issue's forgery: the id of an entry rewritten to lead into another dataset, in
        suite.json, the manifest and every result, every sha256 recomputed to match. Before,
        report.html and three PNGs landed in that dataset, then a traceback."""
        _, folder = suite_copy
        forged = "../datasets/random-3"
        manifest = read_json(folder / "suite-manifest.json")
        manifest["datasets"][forged] = dict(manifest["datasets"].pop("primitives"))
        write_json(folder / "suite-manifest.json", manifest)
        for path in folder.glob("results/*/result.json"):
            result = read_json(path)
            rename_entry(result["datasets"], "primitives", forged)
            write_json(path, result)
        rewrite_everywhere(folder, lambda d: d["scenes"][0].update(id=forged))
        before = snapshot(folder)
        code, _, err = run(capsys, "suite", "report", folder)
        one_line_error(code, err, "suite.json", "id must be a folder name", repr(forged))
        after = snapshot(folder)
        assert {rel: v for rel, v in after.items() if not report_output(rel)} == \
               {rel: v for rel, v in before.items() if not report_output(rel)}
        assert not any(rel.startswith("datasets/") and rel.endswith((".html", "grid.png")) for rel in after)

    @pytest.mark.slow
    def test_an_edited_definition_with_every_hash_recomputed_is_caught_by_the_datasets(self, suite_copy, capsys):
        """A seed changed in the definition, the forger also fixing the manifest's record:
        the dataset's own config.json (hashed in its manifest) still says seed 0."""
        _, folder = suite_copy
        manifest = read_json(folder / "suite-manifest.json")
        manifest["datasets"]["primitives"]["seed"] = 5
        write_json(folder / "suite-manifest.json", manifest)
        rewrite_everywhere(folder, lambda d: d["scenes"][0].update(seed=5))
        code, _, err = run(capsys, "suite", "report", folder)
        one_line_error(code, err, "datasets/primitives", "generated from other settings", "config.json")

    def test_a_hash_that_covers_itself_proves_nothing(self, suite_copy, capsys):
        """suite.json's own sha256 recomputed after an edit: the marker, written from the
        suite file by suite generate, still holds the real one."""
        _, folder = suite_copy
        recorded = read_json(folder / "suite.json")
        recorded["definition"]["description"] = "edited"
        recorded["suite_sha256"] = hashlib.sha256(json_bytes(recorded["definition"])).hexdigest()
        write_json(folder / "suite.json", recorded)
        code, _, err = run(capsys, "suite", "report", folder)
        one_line_error(code, err, ".nerfgauge.json", "another definition")

    @pytest.mark.parametrize("edit, words", [
        (lambda d: d["scenes"][1].update(id="ra\0ndom"), ("id must be a folder name", "\\x00")),
        (lambda d: d["scenes"][1].update(id="a/b"), ("id must be a folder name",)),
        (lambda d: d["scenes"][1].update(id=".hidden"), ("id must be a folder name",)),
        (lambda d: d["scenes"][1].update(id="x" * 300), ("at most 255 bytes",)),
        (lambda d: d["scenes"][1].update(seed=-1), ("seed must be a non-negative integer",)),
        (lambda d: d["scenes"][1].update(seed="3"), ("seed must be a non-negative integer",)),
        (lambda d: d["scenes"][1].update(scene="teapot"), ("unknown scene 'teapot'",)),
        (lambda d: d["scenes"][1]["dataset"].update(width="16"), ("scenes[1]",)),
        (lambda d: d["scenes"][1]["dataset"].update(id="x"), ("unknown field 'id'",)),
        (lambda d: d["scenes"][1]["dataset"].pop("spp"), ("missing field dataset.spp",)),
        (lambda d: d["scenes"][1].update(extra=1), ("unknown field 'extra'",)),
        (lambda d: d.update(name="ti\nny"), ("name must be a folder name",)),
        (lambda d: d.update(scenes={}), ("[[scenes]] must be a non-empty list",)),
        (lambda d: d["scoring"].update(split=7), ("scoring.split",)),
        (lambda d: d["scoring"].update(protocol="mine"), ("scoring.protocol must be one of",)),
        (lambda d: d.update(train={"steps": 3}), ("unknown field 'train'",)),  # methods are not the suite's
    ])
    def test_a_malformed_definition_is_one_line(self, suite_copy, capsys, edit, words):
        _, folder = suite_copy
        rewrite_everywhere(folder, edit)
        code, _, err = run(capsys, "suite", "report", folder)
        one_line_error(code, err, "suite.json", *words)

    @pytest.mark.parametrize("bad", ["ra\0ndom", "a/b", "..", ".x", "", "a\nb", "x" * 256, "\udc80"])
    def test_one_validator_for_an_id_in_a_suite_file_and_read_back(self, tmp_path, bad):
        """The suite file and suite.json refuse the same ids with the same words (one
        function), and accept the same (a name with $ and a backslash, non-ASCII)."""
        from nerfgauge.orchestrate.suite.definition import parse_suite, suite_from_definition

        def suite_file(entry_id):
            data = tomllib.loads(suite_toml("tiny", TINY_DATASET, {"steps": 10}))
            data["scenes"][1]["id"] = entry_id
            return data

        def recorded(suite):
            return {"definition": suite.definition()}

        good = parse_suite(suite_file(r"m$\frac$x-é"), "tiny.toml")
        assert suite_from_definition(recorded(good), "suite.json").sha256 == good.sha256
        with pytest.raises(InputError) as first:
            parse_suite(suite_file(bad), "tiny.toml")
        definition = recorded(good)
        definition["definition"]["scenes"][1]["id"] = bad
        with pytest.raises(InputError) as again:
            suite_from_definition(definition, "suite.json")
        assert str(first.value).split(": id ")[1] == str(again.value).split(": id ")[1]

    @pytest.mark.parametrize("edit, words", [
        (lambda m: m.update(datasets=[]), ("datasets must be an object",)),
        (lambda m: m["datasets"]["primitives"].update(manifest_sha256="x"), ("manifest_sha256 must be a sha256",)),
        (lambda m: m["datasets"]["primitives"].update(path="../elsewhere"), ("datasets.primitives.path",)),
        (lambda m: m["datasets"]["primitives"].update(files=[]), ("files must be an object",)),
        (lambda m: m["datasets"]["primitives"].pop("files"), ("missing field files",)),
        (lambda m: m["datasets"].update({"../x": {}}), ("a dataset the suite does not have",)),
        (lambda m: m["datasets"].update(primitives="x"), ("must be an object",)),
    ])
    def test_a_malformed_suite_manifest_is_one_line(self, suite_copy, capsys, edit, words):
        _, folder = suite_copy
        manifest = read_json(folder / "suite-manifest.json")
        edit(manifest)
        write_json(folder / "suite-manifest.json", manifest)
        code, _, err = run(capsys, "suite", "report", folder)
        one_line_error(code, err, "suite-manifest.json", *words)

    def test_suite_generate_refuses_a_malformed_resume_manifest_and_overwrite_records_it_again(self, suite_copy,
                                                                                                capsys):
        toml, folder = suite_copy
        write_json(folder / "suite-manifest.json", {**read_json(folder / "suite-manifest.json"), "datasets": [1]})
        code, _, err = run(capsys, "suite", "generate", toml, "--out", folder)
        one_line_error(code, err, "suite-manifest.json", "--overwrite")
        code, _, err = run(capsys, "suite", "generate", toml, "--out", folder, "--overwrite")
        assert code == 0, err
        assert isinstance(read_json(folder / "suite-manifest.json")["datasets"], dict)

    @pytest.mark.parametrize("edit, words", [
        (lambda r: r["datasets"]["primitives"].update(metrics="datasets/primitives/scene.json"),
         ("metrics must be 'results/nearest/primitives/metrics.json'",)),
        (lambda r: r["datasets"]["primitives"].update(metrics="../../../etc/passwd"), ("metrics must be",)),
        (lambda r: r.update(method="other"), ("is for method 'other'",)),
        (lambda r: r.update(method="a/b"), ("method must be a folder name",)),
        (lambda r: rename_entry(r["datasets"], "primitives", "../x"), ("dataset ids",)),
        (lambda r: r["datasets"]["primitives"].update(train_seconds=-1), ("train_seconds must be a number >= 0",)),
        (lambda r: r["datasets"]["primitives"].update(ms_per_frame=1e400), ("ms_per_frame must be a number",)),
        (lambda r: r["datasets"]["primitives"].update(geometry={"x": 1}), ("geometry.x",)),
        (lambda r: r.update(skipped=["x"]), ("skipped must be an object",)),
        (lambda r: r.update(failed={"primitives": 3}), ("failed must be an object",)),
        (lambda r: r["datasets"]["primitives"].update(renders="../../datasets/x"), ("renders must be a path",)),
        (lambda r: r["datasets"]["primitives"].update(renders="/etc"), ("renders must lie in",)),
        (lambda r: r.update(seeds=[-1]), ("seeds",)),
        (lambda r: r.update(pred_root=3), ("pred_root must be a path",)),
    ])
    def test_a_malformed_result_is_one_line_and_reads_nothing_outside(self, suite_copy, capsys, edit, words):
        _, folder = suite_copy
        path = folder / "results" / "nearest" / "result.json"
        result = read_json(path)
        edit(result)
        text = json.dumps(result).replace("Infinity", "1e400")  # a finite-looking literal that parses to inf
        path.write_text(text)
        code, _, err = run(capsys, "suite", "report", folder)
        one_line_error(code, err, "result.json", *words)

    @pytest.mark.parametrize("edit, words", [
        (lambda r: r["result"].update(steps="x"), ("steps must be a number",)),
        (lambda r: r["result"].update(seed=9), ("the job's seed is 0",)),
        (lambda r: r["result"].update(threads=0), ("threads must be an integer >= 1",)),
        (lambda r: r["result"].update(geometry={"n/a": 3}), ("n/a must be alone",)),
        (lambda r: r["result"].pop("model_bytes"), ("missing field model_bytes",)),
        (lambda r: r.update(result=[]), ("result must be an object",)),
        (lambda r: r["result"].update(renders="datasets/primitives"), ("renders must lie in predictions/",)),
        (lambda r: r["result"].update(method="nearest"), ("the job's is compact-nerf",)),
    ])
    def test_a_malformed_job_record_is_one_line(self, suite_copy, capsys, edit, words):
        """The record keeps its recipe hash (recomputed by the job from its own inputs, never
        read from the record), so the job counts as finished and its result is read."""
        toml, folder = suite_copy
        path = folder / "jobs" / "compact-nerf" / "primitives.json"
        record = read_json(path)
        edit(record)
        write_json(path, record)
        code, _, err = run(capsys, "suite", "run", toml, "--out", folder)
        one_line_error(code, err, "jobs/compact-nerf/primitives.json", *words)


class TestDerivedNumbersAreFinite:
    @staticmethod
    def metrics(path: Path, psnr, ssim=0.9, **extra) -> Path:
        path.write_text(json.dumps({"schema": 1, "scene": "primitives", "split": "test",
                                    "mean": {"psnr": psnr, "ssim": ssim}, **extra}))
        return path

    def test_the_issues_example_gives_finite_bounds(self, tmp_path, capsys):
        """K = 2, A = 1e-300: the Cauchy (1 degree of freedom) quantile cot(pi A) = 1/(pi A)
        to float precision, times s sqrt(1 + 1/2); ssim's runs agree, so its floor is their
        mean (not nan). check reads the file and passes a good run."""
        c1, c2 = self.metrics(tmp_path / "c1.json", 30.1), self.metrics(tmp_path / "c2.json", 30.5)
        out = tmp_path / "prop.toml"
        code, _, err = run(capsys, "check", "--calibrate", c1, c2, "--false-alarm", "1e-300", "--out", out)
        assert code == 0, err
        table = tomllib.loads(out.read_text())["primitives"]
        s = math.sqrt(((30.1 - 30.3) ** 2 + (30.5 - 30.3) ** 2) / 1)
        expected = 30.3 - (1 / (math.pi * 1e-300)) * s * math.sqrt(1.5)
        assert math.isfinite(table["psnr"]["min"]) and table["psnr"]["min"] == pytest.approx(expected, rel=1e-9)
        assert table["ssim"]["min"] == pytest.approx(0.9, abs=1e-12)
        code, _, err = run(capsys, "check", self.metrics(tmp_path / "new.json", 29.0), "--thresholds", out)
        assert code == 0, err

    @pytest.mark.parametrize("df", [1, 2, 3, 9, 99, 1000])
    @pytest.mark.parametrize("rate", [2.3e-308, 1e-300, 1e-17, 0.05, 0.5, 0.9, 1 - 1e-12])
    def test_the_t_quantile_against_a_50_digit_oracle(self, df, rate):
        """P(T > q) for Student's t from the regularised incomplete beta function in mpmath at
        50 digits (P(|T| > q) = I_x(df/2, 1/2), x = df / (df + q^2)): the quantile gives the
        rate back to 1e-9 relative, across the whole range of normal floats."""
        mpmath = pytest.importorskip("mpmath")
        from nerfgauge.eval.calibrate import t_upper_quantile

        q = t_upper_quantile(rate, df)
        assert math.isfinite(q)
        with mpmath.workdps(50):
            qm = mpmath.mpf(q)
            two_sided = mpmath.betainc(mpmath.mpf(df) / 2, mpmath.mpf(1) / 2, 0, df / (df + qm ** 2),
                                       regularized=True)
            upper = two_sided / 2 if q >= 0 else 1 - two_sided / 2
            assert abs(upper / rate - 1) < 1e-9 or abs(upper - rate) < 1e-15, (float(upper), rate)

    @pytest.mark.parametrize("values, rate, words", [
        ((1e308, -1e308), "0.05", ("beyond float range", "psnr")),
        ((30.0, 31.0), "5e-324", ("--false-alarm must be a number from 2.23e-308",)),
    ])
    def test_what_leaves_float_range_is_one_line(self, tmp_path, capsys, values, rate, words):
        files = [self.metrics(tmp_path / f"c{k}.json", v) for k, v in enumerate(values)]
        out = tmp_path / "prop.toml"
        code, _, err = run(capsys, "check", "--calibrate", *files, "--false-alarm", rate, "--out", out)
        one_line_error(code, err, *words)
        assert not out.exists()

    def test_a_training_median_beyond_float_range_is_one_line(self, tmp_path, capsys):
        files = [self.metrics(tmp_path / f"c{k}.json", 30.0 + k, training={"steps": 400, "steps_per_second": 1.7e308})
                 for k in range(2)]
        out = tmp_path / "prop.toml"
        code, _, err = run(capsys, "check", "--calibrate", *files, "--out", out)
        one_line_error(code, err, "median training speed")
        assert not out.exists()

    def test_scores_whose_mean_leaves_float_range_are_one_line_in_suite_report(self, suite_copy, capsys):
        """Finite but extreme scores (1.5e308 dB in every frame of both datasets): the mean
        over datasets and the bootstrap sums overflow; before, an inf reached the JSON
        writer (a traceback). Now one line naming what overflowed."""
        _, folder = suite_copy
        for path in folder.glob("results/nearest/*/metrics.json"):
            document = read_json(path)
            document["mean"]["psnr"] = 1.5e308
            for frame in document["frames"]:
                frame["psnr"] = 1.5e308
            write_json(path, document)
        code, _, err = run(capsys, "suite", "report", folder)
        one_line_error(code, err, "beyond float range")

    @pytest.mark.parametrize("literal, where", [
        ('{"psnr": NaN}', "mean.psnr"), ('{"psnr": Infinity}', "mean.psnr"), ('{"psnr": -Infinity}', "mean.psnr"),
        ('{"psnr": 1e400}', "mean.psnr"), ('{"psnr": 1' + "0" * 400 + "}", "mean.psnr"),
    ])
    def test_a_non_finite_metric_in_check_is_exit_2_not_a_failed_bound(self, tmp_path, capsys, literal, where):
        path = tmp_path / "metrics.json"
        path.write_text('{"schema": 1, "scene": "primitives", "split": "test", "mean": ' + literal + "}")
        code, out, err = run(capsys, "check", path, "--thresholds", Path(__file__).parents[1] / "thresholds.toml")
        one_line_error(code, err, where)
        assert out == ""

    @pytest.mark.parametrize("extra, where", [
        ({"geometry": {"normal_angle_mean": "NaN"}}, "geometry.normal_angle_mean"),
        ({"ci95": {"psnr": [1.0, "Infinity"]}}, "ci95.psnr"),
        ({"training": {"steps": 400, "seconds": "NaN"}}, "training.seconds"),
    ])
    def test_non_finite_figures_beside_the_means_are_exit_2(self, tmp_path, capsys, extra, where):
        path = tmp_path / "metrics.json"
        text = json.dumps({"schema": 1, "scene": "primitives", "split": "test", "mean": {"psnr": 31.0}, **extra})
        path.write_text(text.replace('"NaN"', "NaN").replace('"Infinity"', "Infinity"))
        code, _, err = run(capsys, "check", path, "--thresholds", Path(__file__).parents[1] / "thresholds.toml")
        one_line_error(code, err, where)


class TestUserStringsAreText:
    @pytest.mark.parametrize("text", [r"m$\frac$x", "$x$", "$$", "a\\$b$", "50$", r"$\alpha", "plain"])
    def test_plain_text_is_drawn_as_written(self, text):
        """matplotlib's own decision (Text._preprocess_math: mathtext or not, and the string
        shown) on the escaped label: never mathtext, and shown exactly as the user wrote it."""
        from matplotlib.figure import Figure

        from nerfgauge.eval.report import plain_text

        label = Figure().text(0, 0, plain_text(text))
        assert label._preprocess_math(label.get_text()) == (text, False)

    @pytest.mark.slow
    def test_the_issues_method_named_like_mathtext_gets_a_report(self, suite_copy, capsys):
        toml, folder = suite_copy
        method = r"m$\frac$x|y"
        code, _, err = run(capsys, "suite", "evaluate", toml, folder, "--method", method,
                           "--pred", folder / "predictions" / "nearest")
        assert code == 0, err
        code, _, err = run(capsys, "suite", "report", folder)
        assert code == 0, err
        assert method in read_json(folder / "leaderboard.json")["methods"]
        row = next(line for line in (folder / "leaderboard.md").read_text().splitlines() if line.startswith("| m$"))
        assert row.startswith(r"| m$\\frac$x\|y |")  # one cell: the | escaped, the backslash too
        for name in ("report.html", "grid.png", "curve.png", "cameras.png"):
            assert (folder / "report" / "primitives" / name).stat().st_size > 0

    def test_the_figures_draw_hostile_names(self, tmp_path):
        from nerfgauge.eval.report import plot_curves
        from nerfgauge.orchestrate.suite.robustness import plot

        names = [r"m$\frac$x", "$", r"a\$b$c"]
        plot_curves({names[0]: [{"seconds": 0.0, "val_psnr": 10.0}, {"seconds": 1.0, "val_psnr": 12.0}]},
                    tmp_path / "curve.png", baselines={names[1]: 11.0}, finals={names[2]: (1.0, 12.5)})
        plot({"curves": [{"group": r"mesh:$\x$.obj seed 0", "field": "exposure_ev", "unit": "EV sd",
                          "levels": [0.0, 1.0], "entries": ["a", "b"],
                          "scores": {name: {"psnr": [20.0, 18.0]} for name in names}}]}, tmp_path / "robustness.png")
        assert (tmp_path / "curve.png").stat().st_size > 0 and (tmp_path / "robustness.png").stat().st_size > 0

    def test_a_report_that_fails_leaves_no_previous_report(self, suite_copy, capsys):
        """A malformed result.json appears after a good report: the report fails in one line,
        and the old leaderboard and per-dataset reports are gone, not left looking current."""
        _, folder = suite_copy
        assert (folder / "leaderboard.html").is_file() and (folder / "report" / "primitives" / "grid.png").is_file()
        path = folder / "results" / "nearest" / "result.json"
        write_json(path, {**read_json(path), "datasets": []})
        code, _, err = run(capsys, "suite", "report", folder)
        one_line_error(code, err, "result.json")
        left = [rel for rel in snapshot(folder) if report_output(rel) and rel != ".nerfgauge.lock"]
        assert left == []

    def test_write_report_removes_the_old_page_before_drawing(self, ran, tmp_path):
        """eval.report.write_report (nerfgauge run's report) failing while drawing the grid
        (a render missing) leaves neither the old report.html nor its figures."""
        from nerfgauge.eval.report import write_report

        _, folder = ran
        out = tmp_path / "report"
        out.mkdir()
        for name in ("report.html", "grid.png", "curve.png", "cameras.png"):
            (out / name).write_bytes(b"old")
        renders = tmp_path / "renders"
        shutil.copytree(folder / "predictions" / "compact-nerf" / "primitives", renders)
        for png in renders.rglob("r_001*.png"):
            png.unlink()
        documents = {"compact-nerf": read_json(folder / "results" / "compact-nerf" / "primitives" / "metrics.json")}
        with pytest.raises(InputError):
            write_report(out / "report.html", "t", folder / "datasets" / "primitives", renders, documents,
                         ours="compact-nerf")
        assert sorted(p.name for p in out.iterdir()) == []

    @pytest.mark.parametrize("edit, words", [
        (lambda t: t.replace('id = "random-3"', 'id = "ra\\u0000ndom"'), ("id must be a folder name", "\\x00")),
        (lambda t: t.replace('id = "random-3"', 'id = "a/b"'), ("id must be a folder name",)),
        (lambda t: t.replace('name = "tiny"', 'name = "ti\\u0000ny"'), ("name must be a folder name",)),
    ])
    def test_nul_or_slash_in_a_suite_id_is_one_line_before_anything_is_written(self, tmp_path, capsys, edit, words):
        toml = tmp_path / "bad.toml"
        toml.write_text(edit(suite_toml("tiny", TINY_DATASET, {"steps": 10})))
        code, _, err = run(capsys, "suite", "generate", toml, "--out", tmp_path / "out")
        one_line_error(code, err, *words)
        assert not (tmp_path / "out").exists()

    def test_a_method_with_a_control_character_is_one_line(self, suite_copy, capsys):
        toml, folder = suite_copy
        code, _, err = run(capsys, "suite", "evaluate", toml, folder, "--method", "a\tb",
                           "--pred", folder / "predictions" / "nearest")
        one_line_error(code, err, "--method must be a folder name")
        assert not (folder / "results" / "a\tb").exists()


class TestGatesCompareLikeWithLike:
    THRESHOLDS = Path(__file__).parents[1] / "thresholds.toml"

    @staticmethod
    def metrics(path: Path, psnr=31.0, **protocol) -> Path:
        path.write_text(json.dumps({"schema": 1, "scene": "primitives", "split": "test",
                                    "mean": {"psnr": psnr, "ssim": 0.97, "opacity_iou": 0.97}, **protocol}))
        return path

    @pytest.mark.parametrize("protocol, words", [
        ({"protocol": "ns-eval", "protocol_background": "black"}, ("ns-eval (colour on black",)),
        ({"protocol": "nerfbaselines", "protocol_background": "white"}, ("nerfbaselines (colour on white",)),
        ({"background": "black"}, ("nerfgauge (colour on black",)),
        ({"depth_kind": "z"}, ("depth z",)),
    ])
    def test_check_refuses_metrics_of_another_protocol_naming_both(self, tmp_path, capsys, protocol, words):
        path = self.metrics(tmp_path / "m.json", **protocol)
        code, out, err = run(capsys, "check", path, "--thresholds", self.THRESHOLDS)
        one_line_error(code, err, *words, "nerfgauge (colour on white, depth distance)", "not comparable")
        assert out == ""

    def test_the_repository_thresholds_record_our_protocol(self, tmp_path, capsys):
        from nerfgauge.eval.check import ScoringProtocol, bounds_for_scene, load_thresholds

        bounds = bounds_for_scene(load_thresholds(self.THRESHOLDS), "primitives")
        assert {b.protocol for b in bounds} == {ScoringProtocol()} and all(b.protocol.recorded for b in bounds)
        code, out, _ = run(capsys, "check", self.metrics(tmp_path / "m.json"), "--thresholds", self.THRESHOLDS)
        assert "protocol nerfgauge (colour on white, depth distance)" in out.splitlines()[0]
        assert "note" not in out.splitlines()[0]

    def test_calibrate_refuses_mixed_protocols_naming_them(self, tmp_path, capsys):
        ours = self.metrics(tmp_path / "a.json", 31.0)
        theirs = self.metrics(tmp_path / "b.json", 30.0, protocol="ns-eval", protocol_background="black")
        out = tmp_path / "prop.toml"
        code, _, err = run(capsys, "check", "--calibrate", ours, theirs, "--out", out)
        one_line_error(code, err, "2 protocols", "a.json: nerfgauge", "b.json: ns-eval", "not comparable")
        assert not out.exists()

    def test_a_calibrated_file_records_its_protocol_and_check_holds_metrics_to_it(self, tmp_path, capsys):
        runs = [self.metrics(tmp_path / f"r{k}.json", 30.0 + 0.2 * k, protocol="ns-eval", protocol_background="black")
                for k in range(4)]
        out = tmp_path / "prop.toml"
        code, _, err = run(capsys, "check", "--calibrate", *runs, "--out", out)
        assert code == 0, err
        assert tomllib.loads(out.read_text())["protocol"] == {"name": "ns-eval", "background": "black",
                                                              "depth_kind": "distance"}
        code, _, err = run(capsys, "check", runs[3], "--thresholds", out)
        assert code == 0, err
        code, _, err = run(capsys, "check", self.metrics(tmp_path / "ours.json", 40.0), "--thresholds", out)
        one_line_error(code, err, "scored under protocol nerfgauge", "measured under ns-eval")

    def test_an_older_file_without_a_protocol_is_ours_with_a_note(self, tmp_path, capsys):
        old = tmp_path / "old.toml"
        old.write_text("[primitives]\npsnr = { min = 20.0 }\n")
        code, out, err = run(capsys, "check", self.metrics(tmp_path / "m.json"), "--thresholds", old)
        assert code == 0, err
        assert "records no [protocol]" in out.splitlines()[0] and "read as ours" in out.splitlines()[0]
        assert sum("records no [protocol]" in line for line in out.splitlines()) == 1
        code, _, err = run(capsys, "check", self.metrics(tmp_path / "ns.json", protocol="ns-eval",
                                                         protocol_background="black"), "--thresholds", old)
        one_line_error(code, err, "ns-eval", "nerfgauge (colour on white")

    @pytest.mark.parametrize("protocol, words", [
        ({"protocol": "ns-eval", "protocol_background": "white"}, ("composites onto black",)),
        ({"protocol": "mine"}, ("protocol must be one of",)),
        ({"depth_kind": "disparity"}, ("depth_kind must be one of",)),
    ])
    def test_a_metrics_file_contradicting_a_protocol_is_one_line(self, tmp_path, capsys, protocol, words):
        code, _, err = run(capsys, "check", self.metrics(tmp_path / "m.json", **protocol),
                           "--thresholds", self.THRESHOLDS)
        one_line_error(code, err, *words)

    def test_the_api_gate_compares_protocols_too(self, tmp_path):
        from nerfgauge import api

        document = {"schema": 1, "scene": "primitives", "split": "test", "mean": {"psnr": 31.0, "opacity_iou": 0.97,
                                                                              "ssim": 0.97},
                    "protocol": "ns-eval", "protocol_background": "black"}
        with pytest.raises(InputError, match="not comparable"):
            api.check(document, self.THRESHOLDS)
        results = api.check({**document, "protocol": "nerfgauge", "protocol_background": "white"}, self.THRESHOLDS)
        assert {r.metric: r.passed for r in results}["psnr"] is True
