"""benchmarks/regression.py: its cases, its committed baseline, and one real case timed against another install."""
import importlib.util
import json
import sys

from tests.helpers import REPO


def _regression():
    """The script as a module (registered, as its dataclasses need), with the
    benchmarks' folder on the path for the scripts it imports."""
    if "regression_benchmark" in sys.modules:
        return sys.modules["regression_benchmark"]
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        spec = importlib.util.spec_from_file_location("regression_benchmark", REPO / "benchmarks/regression.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules["regression_benchmark"] = module
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(REPO / "benchmarks"))


def test_every_case_has_a_baseline_and_the_quick_ones_cover_every_path():
    regression = _regression()
    names = [case.name for case in regression.CASES]
    assert len(set(names)) == len(names)
    baseline = json.loads(regression.BASELINE.read_text())
    assert set(baseline["cases"]) == set(names), "a case without a baseline is never compared"
    assert all(entry["units"] > 0 and entry["seconds"] > 0 for entry in baseline["cases"].values())
    quick = {case.name for case in regression.CASES if case.quick}
    # every path a user waits on: help, a run, keypoints (affine, pinhole), photos, a sweep
    assert {"startup", "run", "orthographic_200k", "bundle_250", "photos_10", "reproduce_tiny"} <= quick


def test_a_case_is_timed_beside_another_install_and_flagged_against_its_baseline(tmp_path, capsys):
    """``--against`` with the same install: the same-run ratio is near 1, the
    JSON line and the table say so, and a baseline it beats is not flagged."""
    from tests.helpers import mpe3d_command

    regression = _regression()
    command = mpe3d_command()[0]
    code = regression.main(["--cases", "startup", "--mpe3d", command, "--against", command,
                            "--work", str(tmp_path)])
    out, err = capsys.readouterr()
    line = json.loads(out.strip().splitlines()[-1])
    assert line["case"] == "startup" and line["against_s"] > 0 and line["seconds"] > 0
    # the ratio of the unrounded times: the rounded ones' within their last digit
    assert abs(line["same_run_ratio"] - line["seconds"] / line["against_s"]) < 0.02
    assert "| startup |" in err and "same run" in err
    assert code == int(line["slower"])
