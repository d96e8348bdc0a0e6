import subprocess
import sys

import pytest

from mpe3d.errors import MpeError
from mpe3d.harness.experiment.config import config_from_file, make_config, parse_override, read_yaml


def test_defaults_are_complete_and_documented():
    cfg = make_config()
    flat = cfg.flat()
    assert flat["shape"] == "chair" and flat["points"] == 512 and flat["views"] == 4
    assert flat["solver.name"] == "sgd" and flat["solver.max_iter"] == 300
    assert cfg.nested()["visibility"] == {"mode": "exact", "k": 3, "count": None, "n_rays": None,
                                          "min_views": 0}


def test_keys_added_later_leave_earlier_hashes_alone():
    base = make_config({"points": 256})
    explicit = make_config({"points": 256, "view_layout": "band", "visibility.min_views": 0,
                            "visibility.n_rays": None, "noise.views": "one"})
    assert explicit.hash() == base.hash()  # cached runs from before the keys existed still count
    assert make_config({"points": 256, "view_layout": "sphere"}).hash() != base.hash()
    assert make_config({"points": 256, "visibility.min_views": 2}).hash() != base.hash()
    with pytest.raises(MpeError, match="visibility.min_views: must be between 0 and views=4"):
        make_config({"visibility.min_views": 5})


def test_overrides_parse_as_yaml_scalars():
    assert parse_override("points=256") == ("points", 256)
    assert parse_override("angle_range=90") == ("angle_range", 90)
    assert parse_override("shape=chair") == ("shape", "chair")
    cfg = make_config(dict(parse_override(x) for x in ["solver=baseline", "angle_range=90"]))
    assert cfg.solver == "baseline" and cfg["angle_range"] == 90.0


def test_hash_is_canonical_and_stable_across_processes():
    a = make_config({"points": 256, "solver.max_iter": 100})
    b = make_config({"solver.max_iter": 100, "points": 256})
    assert a.hash() == b.hash()
    assert a.hash() != make_config({"points": 256}).hash()
    code = ("from mpe3d.harness.experiment.config import make_config;"
            "print(make_config({'points': 256, 'solver.max_iter': 100}).hash())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={"PYTHONHASHSEED": "123", "PATH": ""})
    assert out.stdout.strip() == a.hash()


def test_solver_change_keeps_the_other_values():
    cfg = make_config({"points": 300}).replace(**{"solver": "baseline"})
    assert cfg["points"] == 300 and cfg.solver == "baseline"
    assert "solver.max_iter" in cfg.flat() and "solver.c" not in cfg.flat()


def test_yaml_exponent_without_dot_is_a_number():
    # PyYAML reads 1e-12 as a string (YAML 1.1); a user means the number.
    assert make_config({"solver.tol": "1e-12", "noise.fraction": "2e-1"})["solver.tol"] == 1e-12
    with pytest.raises(MpeError, match="expected a number"):
        make_config({"noise.fraction": "nan"})


@pytest.mark.parametrize("overrides, message", [
    ({"viws": 3}, "unknown key 'viws' (did you mean 'views'?)"),
    ({"points": "many"}, "points: expected an integer, got 'many'"),
    ({"points": 3}, "points: must be at least 4, got 3"),
    ({"views": 1}, "views: must be at least 2, got 1"),
    ({"views": 3, "visibility.k": 4}, "visibility.k: must be between 1 and views=3, got 4"),
    ({"visibility.mode": "exactly"}, "'exactly' is not one of all, exact, count, raytrace, zbuffer (did you mean 'exact'?)"),
    ({"solver": "sdg"}, "unknown solver 'sdg' (known: baseline, factorize, refine, sgd) (did you mean 'sgd'?)"),
    ({"solver.max_itr": 5}, "unknown option 'solver.max_itr' for solver 'sgd' (options: "),
    ({"solver.max_iter": 2.5}, "solver.max_iter: expected an integer >= 0 for solver 'sgd', got 2.5"),
    ({"noise.fraction": 1.5}, "noise.fraction: must be in [0, 1]"),
])
def test_bad_values_name_the_culprit(overrides, message):
    with pytest.raises(MpeError) as err:
        make_config(overrides)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_yaml_config_nested_or_dotted(tmp_path):
    path = tmp_path / "run.yaml"
    path.write_text("shape: torus\nvisibility:\n  mode: all\nsolver:\n  name: sgd\n  max_iter: 50\n"
                    "noise.type: distance\n")
    cfg = config_from_file(path)
    assert cfg["visibility.mode"] == "all" and cfg["solver.max_iter"] == 50
    assert cfg["noise.type"] == "distance"


def test_malformed_yaml_names_file_and_line(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("shape: torus\npoints: [1, 2\nviews: 3\n")
    with pytest.raises(MpeError, match=r"malformed YAML at .*bad.yaml:\d+"):
        read_yaml(path)
    with pytest.raises(MpeError, match="cannot read config file"):
        read_yaml(tmp_path / "missing.yaml")


@pytest.mark.parametrize("text, message", [
    ("shape: torus\nviws: 3\n", "unknown key 'viws' at {}:2 (did you mean 'views'?)"),
    ("shape: torus\nvisibility:\n  mode: all\n  k: many\n", "visibility.k: expected an integer, got 'many' at {}:4"),
    ("solver: sdg\n", "unknown solver 'sdg' (known: baseline, factorize, refine, sgd) at {}:1 (did you mean 'sgd'?)"),
    ("points: 64\nsolver:\n  name: sgd\n  max_itr: 5\n", "unknown option 'solver.max_itr' for solver 'sgd'"),
])
def test_config_file_errors_name_file_and_line(tmp_path, text, message):
    path = tmp_path / "run.yaml"
    path.write_text(text)
    with pytest.raises(MpeError) as err:
        config_from_file(path)
    assert message.format(path) in str(err.value)


def test_config_file_then_overrides(tmp_path):
    path = tmp_path / "run.yaml"
    path.write_text("shape: torus\npoints: 64\n")
    cfg = config_from_file(path, {"points": 100})
    assert cfg["shape"] == "torus" and cfg["points"] == 100
