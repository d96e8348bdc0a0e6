"""Hostile input, by class: each gets one line naming the culprit, exit code 2,
no traceback, and nothing written (in-process through ``main``, for speed)."""
import json
import zipfile

import numpy as np
import pytest

from mpe3d.cli import main
from mpe3d.harness.files import write_together

GOOD_XY = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]


def views_json(first=None, ids0=(0, 1, 2, 3)):
    first = GOOD_XY if first is None else first
    return {"views": [{"ids": list(ids0), "xy": first}, {"ids": [0, 1, 2, 3], "xy": GOOD_XY}]}


def good_npz(path, **override):
    arrays = {"view0_ids": np.arange(4), "view0_xy": np.array(GOOD_XY),
              "view1_ids": np.arange(4), "view1_xy": np.array(GOOD_XY), **override}
    np.savez(path, **arrays)
    return path


def truncated_npz(tmp_path):
    path = good_npz(tmp_path / "in.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def corrupt_crc_npz(tmp_path):
    """A valid archive whose member's bytes no longer match their CRC."""
    path = tmp_path / "in.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
        for name, value in (("view0_ids", np.arange(4)), ("view0_xy", np.array(GOOD_XY)),
                            ("view1_ids", np.arange(4)), ("view1_xy", np.array(GOOD_XY))):
            with archive.open(name + ".npy", "w") as handle:
                np.lib.format.write_array(handle, value)
    data = bytearray(path.read_bytes())
    spot = data.rfind(np.array(GOOD_XY).tobytes()[:16])
    data[spot + 3] ^= 0xFF  # one flipped byte in view1_xy's data
    path.write_bytes(bytes(data))
    return path


def object_npz(tmp_path):
    return good_npz(tmp_path / "in.npz", view1_xy=np.array([object(), 1.0] * 4, dtype=object))


def declared_huge_npz(tmp_path):
    """A member whose header claims 10^7 x 10^7 floats (its data is absent)."""
    path = tmp_path / "in.npz"
    good_npz(path)
    header = {"descr": "<f8", "fortran_order": False, "shape": (10**7, 10**7)}
    with zipfile.ZipFile(path, "a") as archive, archive.open("view2_dist.npy", "w") as handle:
        np.lib.format.write_array_header_1_0(handle, header)
    with zipfile.ZipFile(path, "a") as archive:
        with archive.open("view2_ids.npy", "w") as handle:
            np.lib.format.write_array(handle, np.arange(4))
    return path


def write_text(name, text, encoding="utf-8"):
    def make(tmp_path):
        path = tmp_path / name
        path.write_bytes(text.encode(encoding) if isinstance(text, str) else text)
        return path
    return make


def write_json(data):
    return write_text("in.json", json.dumps(data))


RECONSTRUCT_INPUTS = [
    # NPZ members that fail only when read
    (truncated_npz, "not an NPZ file"),
    (corrupt_crc_npz, "member 'view1_xy' cannot be read"),
    (object_npz, "member 'view1_xy' holds Python objects"),
    (declared_huge_npz, "member 'view2_dist' need about"),
    (lambda p: good_npz(p / "in.npz", view0_xy=np.array(GOOD_XY) > 0), "holds a non-numeric value (bool)"),
    (lambda p: good_npz(p / "in.npz", view0_xy=np.array(GOOD_XY) + 1j), "holds a non-numeric value (complex128)"),
    # JSON nested too deep, not UTF-8, ragged rows, booleans where numbers belong
    (write_text("in.json", "[" * 100_000 + "]" * 100_000), "nested too deeply"),
    (write_text("in.json", json.dumps(views_json()).replace("views", "vïews"), "latin-1"), "not a UTF-8 text file"),
    (write_json(views_json([[0, 0], [1, 0, 5], [0, 1], [1, 1]])), "xy row 1 has 3 entries, row 0 has 2"),
    (write_json(views_json([[0, 0], [1, 0], [0, True], [1, 1]])), "xy holds a non-numeric value (row 2: true/false)"),
    (write_json(views_json(ids0=(0, 1, True, 3))), "ids must be a list of integers or strings"),
    (write_json(views_json([[0, 0], [1, 0], [0, 1e400], [1, 1]])), "xy row 2 is not a finite number"),
    # a CSV header naming a column twice
    (write_text("in.csv", "view,point,x,y,x\n0,1,0,0,5\n"), "names column 'x' twice (columns 3 and 5)"),
    (write_text("in.csv", "view,point,x,y\n0,1,0,0\n".encode("utf-16")), "not a UTF-8 CSV file"),
    # point ids too large for an integer
    (write_json(views_json(ids0=(0, 1, 2, 10**30))), "point id '1000000000000000000000000000000' is an integer too large"),
    (write_text("in.csv", "view,point,x,y\n" + "".join(
        f"{k},{i},{x},{y}\n" for k in (0, 1) for i, (x, y) in zip((1, 2, 3, 99999999999999999999), GOOD_XY))),
     "point id '99999999999999999999' is an integer too large"),
]


@pytest.mark.parametrize("make, message", RECONSTRUCT_INPUTS)
def test_hostile_reconstruct_input(tmp_path, capsys, make, message):
    source = make(tmp_path)
    out, report = tmp_path / "cloud.ply", tmp_path / "report.json"
    code = main(["reconstruct", str(source), "--out", str(out), "--report", str(report)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists() and not report.exists()


def good_csv(tmp_path):
    path = tmp_path / "in.csv"
    path.write_text("view,point,x,y\n" + "".join(
        f"{k},{i},{x},{y}\n" for k in (0, 1) for i, (x, y) in enumerate(GOOD_XY)))
    return path


@pytest.mark.parametrize("flags, message", [
    (["--seed", "-1"], "--seed: expected an integer >= 0, got -1"),
    (["--out", "{tmp}"], "the folder holds other files; a COLMAP model goes into a new or empty"),
    (["--out", "{tmp}/folder.ply"], "is a folder, not a file"),
    (["--out", "/proc/cloud.ply"], "cannot write in /proc"),
    (["--report", "{tmp}/missing/report.json"], "folder {tmp}/missing does not exist"),
    (["--report", "{tmp}/folder.ply"], "is a folder, not a file"),
    (["--report", "{tmp}/report.txt"], "unknown output format '.txt' (expected .json)"),
    (["--report", "/proc/report.json"], "cannot write in /proc"),
    (["--report", "{tmp}/cloud.ply"], "unknown output format"),
    (["--out", "{tmp}/c.json", "--report", "{tmp}/c.json"], "unknown output format '.json'"),
])
def test_output_paths_are_checked_before_any_work(tmp_path, capsys, flags, message):
    source = good_csv(tmp_path)
    (tmp_path / "folder.ply").mkdir()
    flags = [f.format(tmp=tmp_path) for f in flags]
    if "--out" not in flags:
        flags += ["--out", str(tmp_path / "cloud.ply")]
    before = sorted(p.name for p in tmp_path.iterdir())
    code = main(["reconstruct", str(source), *flags])
    err = capsys.readouterr().err
    assert code == 2 and message.format(tmp=tmp_path) in err, err
    assert len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written, no probe left


def test_large_ids_for_a_ply_are_refused_before_the_solve(tmp_path, capsys):
    path = tmp_path / "in.csv"
    path.write_text("view,point,x,y\n" + "".join(
        f"{k},{i},{x},{y}\n" for k in (0, 1) for i, (x, y) in zip((1, 2, 3, 2**40), GOOD_XY)))
    code = main(["reconstruct", str(path), "--out", str(tmp_path / "c.ply"), "--solver", "sgd"])
    err = capsys.readouterr().err
    assert code == 2 and "do not fit a PLY int; write .csv or .npy" in err
    assert main(["reconstruct", str(path), "--out", str(tmp_path / "c.csv")]) == 0


def test_cloud_and_report_are_written_together(tmp_path):
    """If the second file cannot be written, the first is not left behind, and
    an older version of it is put back."""
    cloud, report = tmp_path / "c.csv", tmp_path / "r.json"

    def broken(temp):
        temp.write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError):
        write_together([(cloud, lambda t: t.write_text("new cloud")), (report, broken)])
    assert list(tmp_path.iterdir()) == []
    cloud.write_text("old cloud")
    report.write_text("old report")
    real_replace = __import__("os").replace
    calls = []

    def failing_second_rename(src, dst):
        calls.append(dst)
        if str(dst) == str(report) and str(src).endswith(".tmp"):
            raise OSError("rename failed")
        return real_replace(src, dst)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("mpe3d.harness.files.os.replace", failing_second_rename)
        with pytest.raises(OSError, match="rename failed"):
            write_together([(cloud, lambda t: t.write_text("new cloud")),
                            (report, lambda t: t.write_text("new report"))])
    assert cloud.read_text() == "old cloud" and report.read_text() == "old report"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv", "r.json"]


# -- YAML and sizes --------------------------------------------------------------

YAML_INPUTS = [
    ("name: x\nbase: {shape: torus}\nbase: {views: 3}\n", "duplicate key 'base' at {path}:3 (first at line 2)"),
    ("base:\n  points: 64\n  visibility: {k: 2}\n  visibility.k: 3\n",
     "duplicate key 'base.visibility.k' at {path}:4 (first at line 3)"),
    ("grid: {views: [2, 3, 4, 5, 6, 7, 8, 9, 10, 11], points: [10, 11, 12, 13, 14, 15, 16, 17, 18, 19]}\n"
     "repeats: 1000000\n", "the grid has 100,000,000 runs, over the limit of 100,000 (--max-runs N lifts it)"),
    ("base: {shape: torus, points: 1000000000}\n", "points=1000000000: the exact EMD's"),
    ("a: " + "[" * 5000 + "]" * 5000 + "\n", "{path}"),
    ("a: &a [x, x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
     "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
     "e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d, *d]\nf: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e, *e]\n",
     "expands to over 1,000,000 values"),
    ("name: x\n" + "# padding\n" * 120_000, "is 1.1 MiB, over the limit of 1 MiB for a hand-written YAML file (--max-yaml-mb lifts it)"),
]


@pytest.mark.parametrize("text, message", YAML_INPUTS)
def test_hostile_sweep_files(tmp_path, capsys, text, message):
    path = tmp_path / "s.yaml"
    path.write_text(text)
    code = main(["sweep", str(path), "--dry-run"])
    err = capsys.readouterr().err
    assert code == 2 and message.format(path=path) in err, err
    assert len(err.strip().splitlines()) == 1


def test_limits_are_lifted_by_their_flags(tmp_path, capsys):
    path = tmp_path / "s.yaml"
    path.write_text("name: x\nbase: {shape: torus, points: 64}\nrepeats: 30\n" + "# pad\n" * 200_000)
    assert main(["sweep", str(path), "--dry-run", "--max-runs", "10", "--max-yaml-mb", "5"]) == 2
    assert "the grid has 30 runs, over the limit of 10" in capsys.readouterr().err
    assert main(["sweep", str(path), "--dry-run", "--max-yaml-mb", "5"]) == 0
    assert "30 runs in all" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["run", "points=1000000000"], "points=1000000000: the exact EMD's"),
    (["run", "--config", "/dev/zero"], "config file /dev/zero is not a regular file"),
    (["reconstruct", "/dev/zero", "--out", "c.ply"], "/dev/zero: not a regular file"),
])
def test_hostile_run_arguments(tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    code = main(args)
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert list(tmp_path.iterdir()) == []


def test_duplicate_keys_in_a_run_config(tmp_path, capsys):
    path = tmp_path / "c.yaml"
    path.write_text("shape: torus\npoints: 64\npoints: 128\n")
    assert main(["run", "--config", str(path)]) == 2
    assert f"duplicate key 'points' at {path}:3 (first at line 2)" in capsys.readouterr().err
