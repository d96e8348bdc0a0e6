"""Sweep files: expansion, hashes, and every validation error (in-process, fast)."""
import subprocess
import sys
import textwrap

import pytest

from mpe3d.cli import main
from mpe3d.errors import MpeError
from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.experiment.sweep import load_sweep
from tests.helpers import REPO, SHARED


def write(tmp_path, text, name="s.yaml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text).lstrip())
    return path


def test_grid_zip_repeats_count_and_configs(tmp_path):
    path = write(tmp_path, """
        name: count
        base:
          shape: torus
          points: 64
          visibility: {mode: exact}
          solver: {name: sgd, max_iter: 20}
        grid:
          projections: [fixed, variable]
          noise.type: [none, distance]
        zip:
          views: [3, 4, 5]
          visibility.k: [2, 3, 3]
        repeats: 2
        """)
    sweep = load_sweep(path)
    assert len(sweep.runs) == 2 * 2 * 3 * 2
    combos = {(c["projections"], c["noise.type"], c["views"], c["visibility.k"], c["seed"])
              for c in sweep.runs}
    assert len(combos) == 24
    assert {(v, k) for _, _, v, k, _ in combos} == {(3, 2), (4, 3), (5, 3)}  # zipped, not crossed
    assert {c["seed"] for c in sweep.runs} == {0, 1}
    assert all(c["solver.max_iter"] == 20 and c["points"] == 64 for c in sweep.runs)
    assert sweep.name == "count"
    assert set(sweep.varying) == {"projections", "noise.type", "views", "visibility.k", "seed"}


def test_seeds_zip_groups_and_mapping_items(tmp_path):
    path = write(tmp_path, """
        base: {shape: box, points: 64}
        grid:
          solver: [{name: baseline, method: classical}, {name: sgd, max_iter: 10}]
        zip:
          - {views: [3, 4], visibility.k: [2, 3]}
          - {noise.type: [distance, correspondence], noise.fraction: [0.1, 0.2]}
        seeds: [7, 11]
        """)
    sweep = load_sweep(path)
    assert sweep.name == "s"  # the file's stem when no name is given
    assert len(sweep.runs) == 2 * 2 * 2 * 2
    assert {c["seed"] for c in sweep.runs} == {7, 11}
    assert {c.solver for c in sweep.runs} == {"baseline", "sgd"}
    assert all(c["solver.method"] == "classical" for c in sweep.runs if c.solver == "baseline")
    assert {(c["noise.type"], c["noise.fraction"]) for c in sweep.runs} == {
        ("distance", 0.1), ("correspondence", 0.2)}


def test_duplicate_grid_points_collapse(tmp_path):
    path = write(tmp_path, """
        base: {shape: torus, points: 64}
        grid: {views: [3, 3, 4], points: [64]}
        """)
    sweep = load_sweep(path)
    assert len(sweep.runs) == 2 and sweep.collapsed == 1


def test_sweep_hash_matches_run_config_hash(tmp_path):
    path = write(tmp_path, "base: {shape: torus, points: 64, views: 3, visibility.k: 2}\n")
    (config,) = load_sweep(path).runs
    same = make_config({"shape": "torus", "points": 64, "views": 3, "visibility.k": 2})
    assert config.hash() == same.hash()
    assert config.hash() != same.replace(seed=1).hash()


def test_hash_is_stable_across_processes_and_pinned():
    """The cache key must not depend on the process (PYTHONHASHSEED, dict order)
    or drift between releases by accident: a changed value means every tracked
    run would be recomputed, so it must be a deliberate SCHEMA_VERSION bump."""
    code = ("from mpe3d.harness.experiment.config import make_config;"
            "print(make_config({'views': 5, 'visibility.k': 2, 'solver.max_iter': 7,"
            " 'noise.type': 'distance', 'noise.fraction': 0.25}).hash())")
    hashes = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             env={"PYTHONHASHSEED": seed, "PATH": ""}, cwd=REPO).stdout.strip()
              for seed in ("0", "1", "12345")}
    assert len(hashes) == 1
    here = make_config({"noise.fraction": 0.25, "noise.type": "distance", "solver.max_iter": 7,
                        "visibility.k": 2, "views": 5}).hash()
    assert hashes == {here}
    assert here == "11c921e3ed660c8a"


@pytest.mark.parametrize("text, message", [
    ("grid:\n  viws: [2, 3]\n", "unknown key 'viws' at {}:2 (did you mean 'views'?)"),
    ("gird:\n  views: [2]\n", "unknown key 'gird' at {}:1 (did you mean 'grid'?)"),
    ("base:\n  points: 64\n  solver: {name: sdg}\n", "unknown solver 'sdg' (known: baseline, factorize, refine, sgd) at {}:3"),
    ("grid:\n  views: 4\n", "grid.views: expected a list of values, got 4"),
    ("grid:\n  views: []\n", "grid.views: empty list at {}:2"),
    ("grid:\n  views: [3, 4]\n  projections: []\n", "grid.projections: empty list at {}:3"),
    ("zip:\n  views: [2, 3]\n  visibility.k: [1]\n", "zip: lists differ in length (views has 2, visibility.k has 1)"),
    ("grid:\n  views:\n    - 3\n    - many\n", "views: expected an integer, got 'many' at {}:4"),
    ("grid:\n  visibility.mode: [exact, exactly]\n", "'exactly' is not one of all, exact, count, raytrace, zbuffer at {}:2 (did you mean 'exact'?)"),
    ("grid: {views: [2, 3]\n", "malformed YAML at {}:"),
    ("name: x\n  bad: indent\n", "malformed YAML at {}:"),
    ("base: {views: 2}\ngrid:\n  visibility.k: [1, 3]\n", "visibility.k: must be between 1 and views=2, got 3 at {}:3"),
    ("grid:\n  shape: [chair, chiar]\n", "unknown shape 'chiar'"),
    ("base: {shape: /no/such/mesh.ply}\n", "no mesh file at /no/such/mesh.ply at {}:1"),
    ("grid:\n  solver: [{name: sgd, max_itr: 3}]\n", "unknown option 'solver.max_itr' for solver 'sgd'"),
    ("grid:\n  views: [3]\nzip:\n  views: [4]\n", "key 'views' varies in two places"),
    ("repeats: 0\n", "repeats: expected a positive integer, got 0 at {}:1"),
    ("repeats: 2\nseeds: [1]\n", "give either repeats or seeds, not both"),
    ("seeds: [1, x]\n", "seeds: expected integers >= 0, got 'x' at {}:1"),
    ("base: {seed: 3}\nrepeats: 2\n", "seed is set by repeats/seeds; do not set it here too at {}:1"),
    ("name: [a]\n", "name: expected a non-empty string"),
    ("- views\n- points\n", "a sweep must be a mapping"),
])
def test_validation_errors_name_file_and_line(tmp_path, capsys, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(MpeError) as err:
        load_sweep(path)
    assert message.format(path) in str(err.value)
    # The command line: one line on stderr, exit code 2, no traceback, no run.
    assert main(["sweep", str(path), "--tracking-uri", f"sqlite:///{tmp_path}/t.db"]) == 2
    err_text = capsys.readouterr().err
    assert err_text.startswith("mpe3d: error: ") and message.format(path) in err_text
    assert err_text.count("\n") == 1 and "Traceback" not in err_text
    assert not (tmp_path / "t.db").exists()


def test_one_bad_file_stops_all_before_any_run(tmp_path, capsys):
    good = write(tmp_path, "base: {shape: torus, points: 64}\n", "good.yaml")
    bad = write(tmp_path, "grid: {viws: [1]}\n", "bad.yaml")
    assert main(["sweep", str(good), str(bad), "--tracking-uri", f"sqlite:///{tmp_path}/t.db"]) == 2
    assert "bad.yaml:1" in capsys.readouterr().err
    assert not (tmp_path / "t.db").exists()


def test_missing_file_and_bad_flags(tmp_path, capsys):
    assert main(["sweep", str(tmp_path / "nope.yaml")]) == 2
    assert "cannot read sweep file" in capsys.readouterr().err
    good = write(tmp_path, "base: {shape: torus, points: 64}\n")
    assert main(["sweep", str(good), "--jobs", "0"]) == 2
    assert "--jobs" in capsys.readouterr().err
    assert main(["sweep", str(good), "--backend", "loky", "--scheduler", "tcp://x:1"]) == 2
    assert "--scheduler needs --backend dask" in capsys.readouterr().err


def test_dry_run_lists_runs_without_tracking(tmp_path, capsys):
    path = write(tmp_path, """
        name: dry
        base: {shape: torus, points: 64}
        grid: {views: [3, 4], projections: [fixed, variable]}
        repeats: 3
        """)
    assert main(["sweep", str(path), "--dry-run", "--tracking-uri", f"sqlite:///{tmp_path}/t.db"]) == 0
    out = capsys.readouterr().out
    assert "dry" in out and "12 runs" in out
    assert all(c.hash() in out for c in load_sweep(path).runs)
    assert not (tmp_path / "t.db").exists()


@pytest.mark.parametrize("path", sorted((REPO / "sweeps").rglob("*.yaml")), ids=lambda p: p.name)
def test_shipped_sweeps_are_valid(path):
    overrides = []
    if path.name == "realdata.yaml":  # its data are the user's, in a folder given on the command line
        if not (SHARED / "realdata").is_dir():
            pytest.skip("needs ../shared/realdata")
        overrides = [f"tracks.root={SHARED / 'realdata'}"]
    full = load_sweep(path, overrides=overrides)
    assert full.runs
    for scale in full.scales[1:]:  # every scale is valid, and smaller than the paper's
        assert 0 < len(load_sweep(path, scale, overrides=overrides).runs) <= len(full.runs)


def test_paper_sweeps_cover_every_experiment_of_the_recipe():
    from mpe3d.reports.paper import RECIPE
    from mpe3d.sweeps import paper_sweeps

    sweeps = [load_sweep(p) for p in paper_sweeps()]
    assert sorted(s.name for s in sweeps) == sorted(e.name for e in RECIPE)
    assert all(set(s.scales) == {"full", "quick", "tiny"} and "Paper" in s.description for s in sweeps)


SCALED = """
    name: scaled
    base: {shape: torus, points: 256, visibility: {mode: exact, k: 2}}
    grid:
      views: [2, 3, 4]
      projections: [fixed, variable]
    repeats: 3
    scale:
      quick:
        base: {points: 64}
        grid: {views: [3]}
        seeds: [5]
      tiny:
        zip: {views: [2, 3], visibility.k: [1, 2]}
    """


def test_scales_override_sections_and_share_the_name(tmp_path):
    path = write(tmp_path, SCALED)
    full, quick = load_sweep(path), load_sweep(path, "quick")
    assert full.scales == ("full", "quick", "tiny") and quick.scale == "quick"
    assert len(full.runs) == 3 * 2 * 3 and {c["points"] for c in full.runs} == {256}
    # quick: base keys merge one by one, a grid key is replaced, seeds replace repeats
    assert len(quick.runs) == 2
    assert {(c["points"], c["views"], c["seed"], c["visibility.k"]) for c in quick.runs} == {(64, 3, 5, 2)}
    assert quick.name == full.name == "scaled"  # one experiment: scales share cached runs


def test_scale_errors_name_the_line_of_the_override(tmp_path):
    path = write(tmp_path, SCALED)
    # tiny adds a zip on top of the file's grid, so views would vary twice
    with pytest.raises(MpeError, match=r"varies in two places.*s.yaml:13"):
        load_sweep(path, "tiny")
    with pytest.raises(MpeError, match=r"has no scale 'quik' \(it has: full, quick, tiny\).*quick"):
        load_sweep(path, "quik")
    bad = write(tmp_path, SCALED.replace("points: 64", "points: 2"), "bad.yaml")
    load_sweep(bad)  # the full scale does not see the override
    with pytest.raises(MpeError, match=r"points: must be at least 4.*bad.yaml:9"):
        load_sweep(bad, "quick")
    for text, message in [("scale: {quick: {name: x}}", r"overrides only base.*not 'name'"),
                          ("scale: {full: {repeats: 1}}", "'full' is the file as written"),
                          ("scale: [quick]", "expected a mapping of scale names")]:
        p = write(tmp_path, "base: {shape: box}\n" + text, "e.yaml")
        with pytest.raises(MpeError, match=message):
            load_sweep(p)
    assert load_sweep(write(tmp_path, "base: {shape: box}", "f.yaml"), "full").scales == ("full",)


def test_seeds_given_on_the_command_line_replace_the_files_repeats_and_back(tmp_path):
    path = write(tmp_path, "base: {points: 16}\nrepeats: 3\n")
    assert [c["seed"] for c in load_sweep(path, overrides=["seeds=[5, 7]"]).runs] == [5, 7]
    path = write(tmp_path, "base: {points: 16}\nseeds: [4, 8]\n", "t.yaml")
    assert [c["seed"] for c in load_sweep(path, overrides=["repeats=2"]).runs] == [0, 1]
