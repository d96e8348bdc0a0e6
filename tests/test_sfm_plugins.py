"""SfM plug-ins: a structure-from-motion method in a file or an installed
package, held to its contract by check-solver, refused a taken name, and
never able to hand the scoring a bad pose."""
import re

import numpy as np
import pytest

import mpe3d
from mpe3d import plugins
from mpe3d.errors import MpeError
from mpe3d.harness.experiment.sfm_contract import synthetic_views
from mpe3d.solvers.sfm.methods import BUILT_IN, SFM_METHODS, SfmPose, SfmResult, get_sfm, run_sfm
from mpe3d.testing import check_sfm
from tests.helpers import REPO, assert_contract_fails, run_cli

EXAMPLE = REPO / "examples" / "sfm_plugin.py"  # the docs' worked example, run as it is

# One break each of the example: (its text, the broken text, what the failure line says)
BREAKS = {
    "skewed": ("rotation=camera.rotation", "rotation=1.01 * camera.rotation",
               ["FAIL result (EXIF focal): SfM method 'skewed' (plug-in skewed (file ",
                "poses['photo_00.jpg'].rotation is not a rotation (|R Rᵀ - I| = 0.02"]),
    "renamed": ("poses = {camera.view:", "poses = {camera.view + '.png':",
                ["FAIL result (EXIF focal): SfM method 'renamed'",
                 "poses name 'photo_00.jpg.png', which is not one of the photos given"]),
    "nan": ("points=result.points[placed]", "points=result.points[placed] * np.nan",
            ["FAIL result (EXIF focal): SfM method 'nan'", "points hold NaN or inf"]),
    "unseeded": ("points=result.points[placed]",
                 "points=result.points[placed] + 1e-3 * np.random.standard_normal(result.points[placed].shape)",
                 ["FAIL seed (EXIF focal): two runs with random_state=0 differ (by up to",
                  "draw every random number from a generator built from random_state"]),
    "mirrored": ("rotation=camera.rotation, translation=camera.translation",
                 "rotation=camera.rotation.T, translation=camera.translation",
                 ["FAIL poses (EXIF focal): a pair of registered photos is", "off the true relative pose"]),
}


def broken(tmp_path, name, old, new):
    """The worked example, renamed and broken in one place."""
    text = EXAMPLE.read_text().replace('"pinhole_bundle"', f'"{name}"')
    assert old in text
    path = tmp_path / f"{name}.py"
    path.write_text(text.replace(old, new, 1))
    return path


def test_the_worked_example_passes_check_solver_and_is_listed():
    out = run_cli("check-solver", "pinhole_bundle", "--plugin", str(EXAMPLE))
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.strip().endswith("pinhole_bundle: 6 of 6 checks pass")
    assert all(line.startswith("PASS ") for line in out.stdout.strip().splitlines()[:-1])
    listing = run_cli("solvers", "--plugin", str(EXAMPLE))
    assert listing.returncode == 0, listing.stderr
    group = listing.stdout.split("structure-from-motion plug-ins:\n")[1]
    assert re.match(r"  pinhole_bundle mpe3d\.reconstruct's bundle adjustment, pinhole camera  "
                    r"\(from plug-in sfm_plugin \(file .*sfm_plugin\.py\)\)", group), group
    assert "structure-from-motion plug-ins" not in run_cli("solvers").stdout  # none installed here


def test_the_guide_quotes_the_worked_example_as_it_is():
    guide = (REPO / "docs" / "guide" / "plugins.md").read_text()
    excerpt = next(block for block in guide.split("```python")[1:] if "pinhole_bundle" in block).split("```")[0]
    quoted = [line for line in excerpt.strip().splitlines() if "..." not in line]
    text = EXAMPLE.read_text()
    assert len(quoted) >= 8 and [line for line in quoted if line not in text] == []


def test_the_worked_example_recovers_the_true_poses():
    plugins.load_file(EXAMPLE)
    views, truth = synthetic_views(3, exif=False)
    result = run_sfm("pinhole_bundle", views, 3)
    assert set(result.poses) == set(truth) and len(result.point_ids) == 60
    assert isinstance(result, mpe3d.SfmResult) and get_sfm("pinhole_bundle").origin.how == "file"
    from mpe3d.harness.scene.metrics import relative_pose_errors

    errors = relative_pose_errors(truth, {n: (p.rotation, p.translation) for n, p in result.poses.items()})
    assert errors.max() < 1e-3  # noise-free pixels: the poses up to the solver's tolerance
    focal = [pose.focal_px for pose in result.poses.values()]
    assert np.allclose(focal, 500.0, rtol=1e-6) and result.poses["photo_00.jpg"].principal_point == (320, 240)


@pytest.mark.parametrize("name", sorted(BREAKS))
def test_each_broken_sfm_contract_is_one_line_naming_it(tmp_path, name):
    old, new, expected = BREAKS[name]
    assert_contract_fails(check_sfm, broken(tmp_path, name, old, new), name, expected)


def test_a_failing_sfm_plugin_exits_1_on_the_command_line(tmp_path):
    out = run_cli("check-solver", "nan", "--plugin", str(broken(tmp_path, "nan", *BREAKS["nan"][:2])))
    assert out.returncode == 1, out.stdout + out.stderr
    assert "FAIL result (no EXIF focal): SfM method 'nan' (plug-in nan (file " in out.stdout
    assert out.stdout.strip().endswith("nan: 0 of 2 checks pass; 2 to fix")


@pytest.mark.parametrize("taken", [*BUILT_IN, "pinhole_bundle", "refine"])
def test_a_taken_sfm_name_is_refused_and_leaves_nothing_behind(tmp_path, taken):
    plugins.load_file(EXAMPLE)
    path = broken(tmp_path, "clash", '"clash"', f'"{taken}"')
    said = (f"sfm '{taken}' is one of mpe3d's own (bundle, colmap, colmap_global); rename yours"
            if taken in BUILT_IN else
            "sfm 'refine' is already a solver of mpe3d itself; rename yours"  # --solver names both kinds
            if taken == "refine" else
            f"sfm '{taken}' is already registered by plug-in sfm_plugin (file {EXAMPLE}); rename yours")
    with pytest.raises(plugins.PluginError, match=rf"^plug-in clash \(file .*clash\.py\): {re.escape(said)}$"):
        plugins.load_file(path)
    assert sorted(SFM_METHODS) == ["pinhole_bundle"] and get_sfm("pinhole_bundle").origin.path == EXAMPLE
    assert not any(origin.name == "clash" for origin in plugins.loaded())


def test_an_installed_sfm_plugin_is_read_from_its_entry_point(tmp_path):
    """A real distribution on the path, its .dist-info declaring the group mpe3d.sfm."""
    site = tmp_path / "site"
    info = site / "mysfm-2.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: mysfm\nVersion: 2.0\n")
    (info / "entry_points.txt").write_text("[mpe3d.sfm]\nmysfm = mysfm\n")
    (site / "mysfm.py").write_text(EXAMPLE.read_text().replace('"pinhole_bundle"', '"mysfm"'))
    env = {"PYTHONPATH": str(site)}
    listing = run_cli("solvers", env=env)
    assert listing.returncode == 0, listing.stderr
    assert "structure-from-motion plug-ins:\n  mysfm " in listing.stdout
    assert f"(from plug-in mysfm (mysfm 2.0, entry point {site / 'mysfm.py'}))" in listing.stdout
    check = run_cli("check-solver", "mysfm", env=env)  # no --plugin: installed
    assert check.returncode == 0 and check.stdout.strip().endswith("mysfm: 6 of 6 checks pass"), check.stdout
    (site / "mysfm.py").write_text("import no_such_module_here\n")
    missing = run_cli("check-solver", "mysfm", env=env)
    assert missing.returncode == 2 and "unknown solver 'mysfm'" in missing.stderr
    assert "plug-in mysfm (mysfm 2.0, entry point" in missing.stderr and "no_such_module_here" in missing.stderr


def test_run_sfm_checks_the_output_and_get_sfm_names_what_exists():
    views, _ = synthetic_views(0, exif=True)
    pose = SfmPose(rotation=np.eye(3), translation=np.zeros(3), focal_px=500.0, principal_point=(320.0, 240.0))
    outputs = {
        "focal": (SfmResult({"photo_00.jpg": SfmPose(np.eye(3), np.zeros(3), 0.0, (320.0, 240.0))},
                            np.zeros(0, int), np.zeros((0, 3))), r"poses\['photo_00.jpg'\].focal_px is 0.0"),
        "stray": (SfmResult({"photo_00.jpg": pose}, np.array([5]), np.zeros((1, 3))),
                  r"point_ids hold 1 id\(s\) no photo has \(e.g. 5\)"),
        "shape": (SfmResult({}, views[0].ids, np.zeros((3, 3))), r"points has shape \(3, 3\); expected \(51, 3\)"),
        "reflection": (SfmResult({"photo_01.jpg": SfmPose(-np.eye(3), np.zeros(3), 1.0, (0, 0))},
                                 np.zeros(0, int), np.zeros((0, 3))),
                       r"poses\['photo_01.jpg'\].rotation is not a rotation .*det -1"),
        "type": ({"poses": {}}, "result is a dict; return an mpe3d SfmResult"),
    }
    for name, (output, message) in outputs.items():
        SFM_METHODS[name] = _method(name, output)
        try:
            with pytest.raises(MpeError, match=rf"^SfM method '{name}': {message}"):
                run_sfm(name, views, 0)
        finally:
            del SFM_METHODS[name]
    with pytest.raises(MpeError, match=r"unknown SfM method 'colmap_globl' .*\(did you mean 'colmap_global'\?\)"):
        get_sfm("colmap_globl")
    with pytest.raises(MpeError, match="'colmap' is one of mpe3d's own SfM methods, not a plug-in"):
        get_sfm("colmap")


def _method(name, output):
    from mpe3d.solvers.sfm.methods import SfmMethod

    return SfmMethod(name, lambda views, *, random_state: output, summary="returns a fixed output")
