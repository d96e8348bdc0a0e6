import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from PIL import Image

from tests.helpers import mpe3d_command, run_cli

CONTRACT = {"config", "cd", "cd_mean", "emd", "emd_mean", "roa", "stress", "iterations",
            "runtime_s", "visible_per_view"}


def test_json_contract(tmp_path):
    out = run_cli("run", "shape=torus", "points=128", "views=3", "visibility.k=2",
                  "solver.max_iter=50", "--json")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 1
    result = json.loads(lines[0])
    assert CONTRACT <= set(result)
    assert result["config"]["points"] == 128 and result["config"]["solver"]["max_iter"] == 50
    assert len(result["visible_per_view"]) == 3 and sum(result["visible_per_view"]) == 2 * 128
    assert result["iterations"] <= 50 and result["runtime_s"] > 0
    assert all(np.isfinite(result[k]) for k in ("cd", "emd", "roa", "stress"))


def test_config_file_and_overrides(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("shape: box\npoints: 64\nsolver: {name: baseline}\n")
    out = run_cli("run", "--config", str(cfg), "points=80", "--json")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["config"]["shape"] == "box" and result["config"]["points"] == 80
    assert result["config"]["solver"]["name"] == "baseline"


def test_readable_summary_and_outputs(tmp_path):
    out = run_cli("run", "shape=torus", "points=100", "--out", str(tmp_path / "o"))
    assert out.returncode == 0, out.stderr
    assert "roa=" in out.stdout and "visible per view" in out.stdout
    truth = trimesh.load(tmp_path / "o" / "ground_truth.ply")
    recon = trimesh.load(tmp_path / "o" / "reconstruction.ply")
    assert len(truth.vertices) == len(recon.vertices) == 100
    image = np.asarray(Image.open(tmp_path / "o" / "comparison.png").convert("L"))
    assert image.shape[0] > 100 and image.std() > 5  # not blank


@pytest.mark.parametrize("args, message", [
    (["viws=3"], "unknown key 'viws' (did you mean 'views'?)"),
    (["points=abc"], "points: expected an integer, got 'abc'"),
    (["points=3"], "points: must be at least 4"),
    (["views=1"], "views: must be at least 2"),
    (["views=3", "visibility.k=5"], "visibility.k: must be between 1 and views=3"),
    (["shape=/nowhere/mesh.ply"], "no mesh file at /nowhere/mesh.ply"),
    (["solver=nope"], "unknown solver 'nope'"),
    (["points"], "expected KEY=VALUE, got 'points'"),
    (["--config", "/nowhere.yaml"], "cannot read config file"),
    (["--bogus"], "unrecognized arguments: --bogus"),
])
def test_bad_input_is_one_line_exit_2(args, message):
    out = run_cli("run", *args)
    assert out.returncode == 2
    assert out.stdout == ""
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and lines[0].startswith("mpe3d: error:")
    assert "Traceback" not in out.stderr


def test_unreadable_mesh_is_one_line(tmp_path):
    bad = tmp_path / "broken.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nend_header\n\x00")
    out = run_cli("run", f"shape={bad}")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "broken.ply" in out.stderr and len(out.stderr.strip().splitlines()) == 1


def test_listing_commands():
    shapes = run_cli("shapes")
    assert shapes.returncode == 0 and "guitar" in shapes.stdout and "rifle" in shapes.stdout
    listed = run_cli("solvers")
    assert listed.returncode == 0
    paper, ours = listed.stdout.split("our solvers:")
    assert paper.startswith("the paper's solvers:")
    assert "  sgd " in paper and "  baseline " in paper and "refine" not in paper
    assert "  refine " in ours and "  factorize " in ours and "  sgd " not in ours
    assert "solver.c=1.0  (a number in (0, 1])" in paper  # each option with its rule


def test_too_many_points_for_memory_is_one_line():
    out = run_cli("run", "shape=box", "points=300000", "visibility.mode=all")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "GiB, more than this machine's" in out.stderr


@pytest.mark.parametrize("args, check", [
    (["visibility.mode=count", "visibility.count=50"], lambda r: r["visible_per_view"] == [50] * 4),
    (["visibility.mode=all", "align=ransac4", "solver=baseline"],
     lambda r: r["visible_per_view"] == [80] * 4 and r["config"]["align"] == "ransac4"),
    (["visibility.mode=raytrace", "shape=chair"], lambda r: all(0 < v < 80 for v in r["visible_per_view"])),
    (["noise.type=correspondence", "noise.fraction=0.5", "projections=variable"],
     lambda r: r["config"]["noise"]["type"] == "correspondence"),
    (["init=random", "solver.max_iter=5", "views=2", "visibility.k=2"], lambda r: r["iterations"] <= 5),
])
def test_run_modes_end_to_end(args, check):
    out = run_cli("run", "shape=torus", "points=80", *args, "--json")
    assert out.returncode == 0, out.stderr
    assert check(json.loads(out.stdout))


def test_unwritable_out_dir_is_one_line(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    out = run_cli("run", "shape=torus", "points=40", "--out", str(blocker / "sub"))
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "cannot write outputs to" in out.stderr


def test_every_option_of_every_subcommand_has_a_one_line_help():
    import argparse

    from mpe3d.cli import build_parser

    (commands,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    for name, parser in commands.choices.items():
        assert commands._choices_actions and parser.description or any(
            c.dest == name and c.help for c in commands._choices_actions), name
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            label = f"mpe3d {name} {'/'.join(action.option_strings) or action.dest}"
            assert action.help and "\n" not in action.help.strip(), label


def test_help_imports_nothing_heavy():
    """`mpe3d --help` and `mpe3d run --help` answer from the light modules: the
    command line may not import numpy, scikit-learn, MLflow or numba to parse."""
    probe = ("import sys; from mpe3d import cli; cli.build_parser(); "
             "print(sorted(m for m in ('numpy', 'sklearn', 'mlflow', 'numba', 'pandas', 'scipy') "
             "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    for args in (["--help"], ["run", "--help"], ["sweep", "--help"]):
        done = subprocess.run(mpe3d_command() + args, capture_output=True, text=True)
        assert done.returncode == 0 and "usage" in done.stdout


def test_report_of_a_sweep_without_its_overrides_says_what_the_experiment_holds(tmp_path):
    """The runs exist, but of other configs: the message counts them and says
    the overrides must match, instead of "run it first"."""
    from mpe3d.cli import main

    sweep = tmp_path / "s.yaml"
    sweep.write_text("name: overridden\nbase: {points: 40, solver: refine}\ngrid:\n  views: [3, 4]\n")
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    assert main(["sweep", str(sweep), "points=36", "--jobs", "1", "--quiet", "--no-artifacts",
                 "--tracking-uri", uri]) == 0
    out = subprocess.run([*mpe3d_command(), "report", "--sweep", str(sweep), "--out", str(tmp_path / "r"),
                          "--tracking-uri", uri], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 1
    assert "no finished runs of sweep" in out.stderr and "run it first" not in out.stderr
    assert "holds 2 finished run(s) of other configs" in out.stderr and "overrides" in out.stderr
    again = subprocess.run([*mpe3d_command(), "report", "--sweep", str(sweep), "points=36", "--out",
                            str(tmp_path / "r"), "--tracking-uri", uri], capture_output=True, text=True,
                           cwd=tmp_path, timeout=300)
    assert again.returncode == 0, again.stderr
