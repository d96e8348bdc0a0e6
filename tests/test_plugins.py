"""Plug-ins: a solver or a dataset in a file or an installed package, used as
ours are, fingerprinted on their own, and never able to break mpe3d."""
import io
import shutil
import textwrap

import numpy as np
import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

import mpe3d
from mpe3d import plugins
from mpe3d.errors import MpeError
from mpe3d.harness.tracking.identity import code_identity, run_code
from mpe3d.solvers import SOLVERS
from tests.helpers import REPO, run_cli, scene_and_observations

PLUGIN = REPO / "tests" / "plugins" / "avgmds.py"


@pytest.fixture
def plugin(tmp_path):
    """A copy of the test plug-in, free to edit."""
    path = tmp_path / "avgmds.py"
    shutil.copy(PLUGIN, path)
    return path


def edited(path, old, new, name=None):
    text = path.read_text()
    assert old in text
    out = path.with_name(f"{name or path.stem}.py")
    out.write_text(text.replace(old, new))
    return out


def test_a_plugin_file_registers_its_solver_and_dataset_with_their_origin(plugin):
    origin = plugins.load_file(plugin)
    spec = SOLVERS["avgmds"]
    assert spec.origin == origin and origin.path == plugin.resolve() and origin.how == "file"
    assert not spec.paper and spec.settings == ("fixed", "variable") and not spec.exact
    _, _, obs = scene_and_observations(points=40)
    result = mpe3d.solve("avgmds", obs, random_state=0)
    assert result.points.shape == (40, 3) and result.runtime_s > 0
    assert result.stress == pytest.approx(mpe3d.solve("avgmds", obs, random_state=0).stress)
    assert result.stress > 0  # left None by the plug-in: the Eq. 1 stress was filled in
    with pytest.raises(MpeError, match=r"solver\.jitter: expected a number >= 0"):
        mpe3d.solve("avgmds", obs, jitter=-1.0)
    # its runs carry its own fingerprint beside ours; ours do not
    code = run_code("avgmds", "blobs:two")
    assert code.startswith(code_identity() + "+avgmds-file/") and code.count("+") == 2
    assert run_code("sgd", "chair") == code_identity()


def test_a_plugin_that_fails_halfway_leaves_nothing_registered(tmp_path):
    path = tmp_path / "half.py"
    path.write_text(textwrap.dedent("""
        import mpe3d

        @mpe3d.register_solver("half_first", summary="registers, then the file fails")
        def first(observations, *, random_state):
            raise NotImplementedError

        raise RuntimeError("the second half is missing")
    """))
    with pytest.raises(plugins.PluginError, match=r"plug-in half \(file .*half\.py\) failed to load "
                                                  r"at half\.py line 8: RuntimeError: the second half"):
        plugins.load_file(path)
    assert "half_first" not in SOLVERS


def test_bad_plugins_are_one_line_naming_the_file_and_exit_2(plugin, tmp_path):
    cases = {
        "broken": (edited(plugin, "import numpy as np", "import numpy as np\n1 / 0", "broken"),
                   r"plug-in broken \(file .*broken\.py\) failed to load at broken\.py line 9: "
                   r"ZeroDivisionError"),
        "clash": (edited(plugin, '"avgmds"', '"sgd"', "clash"),
                  r"plug-in clash .*: solver 'sgd' is already registered by mpe3d itself; rename yours"),
        "empty": (tmp_path / "empty.py", "registers no solver, no dataset and no SfM method"),
        "missing": (tmp_path / "nowhere.py", r"plug-in .*nowhere\.py: no such file"),
        "exits": (edited(plugin, "import numpy as np", "import sys\nsys.exit(3)", "exits"),
                  "failed to load at exits.py line 9: SystemExit: 3"),
    }
    (tmp_path / "empty.py").write_text("import numpy\n")
    for name, (path, message) in cases.items():
        out = run_cli("solvers", "--plugin", str(path))
        assert out.returncode == 2, (name, out.stderr)
        assert len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr, name
        assert out.stderr.startswith("mpe3d: error: ") and __import__("re").search(message, out.stderr), \
            (name, out.stderr)


def test_solvers_lists_plugins_in_their_own_group_and_shapes_lists_datasets(plugin):
    out = run_cli("solvers", "--plugin", str(plugin))
    assert out.returncode == 0, out.stderr
    group = out.stdout.split("from plug-in avgmds (file ")[1]
    assert str(plugin.resolve()) in group.splitlines()[0]
    assert "avgmds" in group and "solver.jitter=0.0  (a number >= 0)" in group
    assert "avgmds" not in out.stdout.split("from plug-in")[0]  # not among ours
    shapes = run_cli("shapes", "--plugin", str(plugin))
    assert "blobs:two, blobs:three" in shapes.stdout and str(plugin.resolve()) in shapes.stdout


def test_an_installed_plugin_that_fails_is_a_warning_and_the_rest_works(tmp_path):
    """A real distribution on the path (its .dist-info with an entry point),
    whose module raises on import, as a half-installed package does."""
    site = tmp_path / "site"
    (site / "brokenplug-1.0.dist-info").mkdir(parents=True)
    (site / "brokenplug-1.0.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: brokenplug\nVersion: 1.0\n")
    (site / "brokenplug-1.0.dist-info" / "entry_points.txt").write_text(
        "[mpe3d.solvers]\nbrokenplug = brokenplug\n")
    (site / "brokenplug.py").write_text("import no_such_module_here\n")
    env = {"PYTHONPATH": str(site)}
    listing = run_cli("solvers", env=env)
    assert listing.returncode == 0, listing.stderr
    assert "refine" in listing.stdout and "sgd" in listing.stdout
    assert "not loaded: plug-in brokenplug (brokenplug 1.0, entry point" in listing.stdout
    assert "ModuleNotFoundError: No module named 'no_such_module_here'" in listing.stdout
    unknown = run_cli("run", "solver=nosuch", "points=40", env=env)
    assert unknown.returncode == 2 and "unknown solver 'nosuch'" in unknown.stderr
    assert "brokenplug" in unknown.stderr and len(unknown.stderr.strip().splitlines()) <= 2
    ours = run_cli("run", "solver=factorize", "points=40", "shape=torus", env=env)
    assert ours.returncode == 0 and "roa=" in ours.stdout
    assert ours.stderr.count("mpe3d: warning: plug-in brokenplug") == 1, ours.stderr


def test_a_dataset_plugin_is_a_shape_of_its_own(plugin):
    out = run_cli("run", "shape=blobs:three", "points=60", "solver=refine", "--json", "--plugin", str(plugin))
    assert out.returncode == 0, out.stderr
    summary = __import__("json").loads(out.stdout)
    assert summary["roa"] < 1e-6 and "+avgmds-file/" in summary["code"]
    for bad, message in (("shape=blobs:four", "dataset 'blobs' has no item 'four' (items: two, three)"),
                         ("shape=blobz:two", "no dataset 'blobz'"),
                         ("visibility.mode=raytrace", "gives surface samples, not a mesh")):
        keys = [bad] if bad.startswith("shape") else ["shape=blobs:two", bad]
        out = run_cli("run", *keys, "--plugin", str(plugin))
        assert out.returncode == 2 and message in out.stderr, out.stderr


def test_datasets_and_samples_are_seeded_and_normalised(plugin):
    from mpe3d.harness.scene.shapes import shape_samples

    plugins.load_file(plugin)
    mesh, a = shape_samples("blobs:two", 50, np.random.default_rng(4))
    _, b = shape_samples("blobs:two", 50, np.random.default_rng(4))
    assert mesh is None and np.array_equal(a, b)
    assert np.linalg.norm(a.max(axis=0) - a.min(axis=0)) == pytest.approx(1.0)


SWEEP = """
name: plug
base: {shape: torus, points: 48, views: 4}
grid: {solver: [refine, avgmds], projections: [fixed, variable]}
"""


def codes(uri):
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("plug").experiment_id])
    newest = sorted((r for r in runs if "mpe3d.config_hash" in r.data.tags and r.info.status == "FINISHED"),
                    key=lambda r: r.info.start_time)
    return {(r.data.params["solver.name"], r.data.params["projections"]): (r.info.run_id, r.data.tags["mpe3d.code"])
            for r in newest}


@pytest.mark.slow  # three real sweeps (the first with two workers): the full suite runs it
def test_editing_a_plugin_reruns_its_runs_and_no_others(plugin, tmp_path):
    path = tmp_path / "plug.yaml"
    path.write_text(SWEEP)
    uri = f"sqlite:///{tmp_path}/t.db"
    first = run_cli("sweep", str(path), "--jobs", "2", "--tracking-uri", uri, "--no-artifacts",
                    "--plugin", str(plugin), cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    before = codes(uri)
    assert len(before) == 4 and {c.split("+")[0] for _, c in before.values()} == {code_identity()}
    plugin.write_text(plugin.read_text() + "\n# a comment: the code is the same\n")
    path.write_text(f"plugins: [{plugin.name}]\n" + SWEEP)  # now named by the file, relative to it
    same = run_cli("sweep", str(path), "--jobs", "1", "--tracking-uri", uri, "--no-artifacts", cwd=tmp_path)
    assert "nothing to run: all 4 runs are already tracked" in same.stdout, same.stdout
    plugin.write_text(plugin.read_text().replace("jitter * random_state", "0.5 * jitter * random_state"))
    again = run_cli("sweep", str(path), "--jobs", "1", "--tracking-uri", uri, "--no-artifacts", cwd=tmp_path)
    assert again.returncode == 0 and "2 finished, 0 failed, 2 skipped" in again.stdout, again.stdout
    after = codes(uri)
    for key, (run_id, code) in before.items():
        if key[0] == "refine":
            assert after[key] == (run_id, code)  # ours: the very same runs
        else:
            assert after[key][0] != run_id and after[key][1] != code and after[key][1].startswith(code_identity())


def test_plugin_on_the_command_line_and_the_solver_axis(plugin, tmp_path):
    sweep = tmp_path / "axis.yaml"
    sweep.write_text("name: axis\nbase: {shape: torus, points: 40}\n"
                     "grid: {solver: [baseline, refine], projections: [fixed, variable]}\n")
    out = run_cli("sweep", str(sweep), "--plugin", str(plugin), "--solver", "avgmds", "--dry-run")
    assert out.returncode == 0, out.stderr
    assert "axis" in out.stdout and "6 runs in all" in out.stdout and out.stdout.count("avgmds") == 2
    single = tmp_path / "single.yaml"
    single.write_text("name: single\nbase: {shape: torus, points: 40, solver: sgd}\n"
                      "grid: {projections: [fixed, variable]}\n")
    out = run_cli("sweep", str(single), "--plugin", str(plugin), "--solver", "avgmds", "--dry-run")
    assert "2 runs in all" in out.stdout  # no solver axis: nothing to add to
    bad = run_cli("sweep", str(sweep), "--solver", "avgmds", "--dry-run")
    assert bad.returncode == 2 and "unknown solver 'avgmds'" in bad.stderr
    yaml = tmp_path / "bad.yaml"
    yaml.write_text("name: bad\nplugins: [nowhere.py]\nbase: {points: 40}\n")
    out = run_cli("sweep", str(yaml), "--dry-run")
    assert out.returncode == 2 and "plugins: plug-in" in out.stderr
    assert "nowhere.py: no such file at" in out.stderr and out.stderr.strip().endswith("bad.yaml:2")


def test_a_plugin_stress_solver_runs_wherever_ours_do(plugin, tmp_path):
    """A plug-in's stress solver is a choice of ``reconstruct --objective
    stress`` and of a ``pipeline=tracks`` sweep, as refine is: the accepted
    solvers come from the registry, not from a list of ours."""
    import json

    from tests.helpers import scaled_track_set

    scaled_track_set(tmp_path / "data")
    out, report = tmp_path / "cloud.ply", tmp_path / "report.json"
    done = run_cli("reconstruct", str(tmp_path / "data" / "keypoints.csv"), "--objective", "stress",
                   "--solver", "avgmds", "--plugin", str(plugin), "--out", str(out), "--report", str(report))
    assert done.returncode == 0, done.stderr
    assert out.is_file() and json.loads(report.read_text())["solver"] == "avgmds"
    sweep = tmp_path / "plugin-tracks.yaml"
    sweep.write_text(f"name: plugin-tracks\nbase:\n  pipeline: tracks\n  tracks.root: {tmp_path / 'data'}\n"
                     "  tracks.path: keypoints.csv\n  tracks.truth: points.csv\n  tracks.objective: stress\n"
                     "grid:\n  solver.name: [avgmds, refine]\n")
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    done = run_cli("sweep", str(sweep), "--plugin", str(plugin), "--jobs", "1", "--quiet", "--tracking-uri", uri,
                   cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    table = run_cli("runs", "plugin-tracks", "--format", "csv", "--tracking-uri", uri, cwd=tmp_path)
    rows = pd.read_csv(io.StringIO(table.stdout))
    assert sorted(rows["solver"]) == ["avgmds", "refine"] and set(rows["status"]) == {"FINISHED"}
