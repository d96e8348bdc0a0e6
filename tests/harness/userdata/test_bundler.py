"""Bundler .out and BAL problem files: read by content, solved from their start, refused in one line."""
import numpy as np
import pytest

from mpe3d import reconstruct
from mpe3d.cli import main
from mpe3d.errors import MpeError
from mpe3d.harness.userdata.bundler import read_bundle_file, write_bal, write_bundler
from mpe3d.harness.userdata.reconstruct import prepare
from mpe3d.solvers.sfm.cameras import exp_so3, radial_cameras
from tests.helpers import similarity_residuals

K, N = 6, 80
WRITERS = {"bal": write_bal, "bundler": write_bundler}


def _problem(rng):
    """Known radial cameras (f, k1, k2 per view), points, and their exact images."""
    X = rng.uniform(-1, 1, (N, 3))
    R = exp_so3(np.c_[0.1 * rng.standard_normal(K), np.linspace(-0.6, 0.6, K),
                      0.05 * rng.standard_normal(K)])
    t = np.c_[0.1 * rng.standard_normal((K, 2)), np.full(K, 5.0)]
    focal = 800 + 50 * rng.random(K)
    distortion = np.c_[-0.1 + 0.02 * rng.standard_normal(K), 0.05 + 0.02 * rng.standard_normal(K)]
    view, point = np.repeat(np.arange(K), N), np.tile(np.arange(N), K)
    seen = (rng.random(len(view)) < 0.8) | ((view - point) % K < 2)  # every point in 2+ views
    view, point = view[seen], point[seen]
    xy = radial_cameras(R, t, focal, distortion).project(X, view, point)
    return dict(X=X, R=R, t=t, focal=focal, distortion=distortion, view=view, point=point, xy=xy)


def _write(kind, path, p, rng, exact_start=False):
    """The file, its start the truth perturbed (or exact), k1 = k2 = 0 when perturbed."""
    jitter = 0.0 if exact_start else 1.0
    WRITERS[kind](path, p["view"], p["point"], p["xy"],
                  p["R"] @ exp_so3(jitter * 0.01 * rng.standard_normal((K, 3))),
                  p["t"] + jitter * 0.01, p["focal"] * (1 + jitter * 0.02),
                  p["distortion"] * (1 - jitter), p["X"] + jitter * 0.01 * rng.standard_normal((N, 3)))
    return path


def _similarity_error(X, truth):
    """Largest distance after the best similarity, relative to the cloud's extent."""
    return float(similarity_residuals(X, truth).max() / np.ptp(truth, axis=0).max())


@pytest.mark.parametrize("kind", ["bal", "bundler"])
def test_reading_gives_back_what_was_written(kind, tmp_path, rng):
    p = _problem(rng)
    views = read_bundle_file(_write(kind, tmp_path / "problem.txt", p, rng, exact_start=True))
    assert len(views) == K
    for k, view in enumerate(views):
        rows = p["view"] == k
        np.testing.assert_array_equal(view["ids"], p["point"][rows])
        np.testing.assert_allclose(view["xy"], p["xy"][rows], rtol=1e-15, atol=1e-12)
        np.testing.assert_allclose(view["start_points"], p["X"][p["point"][rows]], atol=1e-15)
        camera = view["start_camera"]
        np.testing.assert_allclose(camera["rotation"], p["R"][k], atol=1e-14)
        np.testing.assert_allclose(camera["translation"], p["t"][k], atol=1e-14)
        assert camera["focal"] == pytest.approx(p["focal"][k], rel=1e-15)
        np.testing.assert_allclose(camera["distortion"], p["distortion"][k], rtol=1e-15)


@pytest.mark.parametrize("kind", ["bal", "bundler"])
def test_noise_free_files_reconstruct_exactly_with_k1_k2_recovered(kind, tmp_path, rng):
    p = _problem(rng)
    result = reconstruct(_write(kind, tmp_path / f"problem.{kind}", p, rng))
    assert result.facts["camera"] == "radial" and result.facts["converged"]
    assert result.facts["reprojection_rms_px"] < 1e-6
    placed = ~np.isin(result.ids, result.unplaced)
    assert _similarity_error(result.points[placed], p["X"][result.ids[placed]]) < 1e-6
    for k, camera in enumerate(result.cameras):
        assert int(camera.view) == k
        np.testing.assert_allclose([camera.k1, camera.k2], p["distortion"][k], rtol=1e-6)
        # the focal length is fixed up to the cloud's scale, which the similarity takes
    recovered = np.array([c.focal_px for c in result.cameras])
    np.testing.assert_allclose(recovered / recovered[0], p["focal"] / p["focal"][0], rtol=1e-6)


def test_the_cli_reads_a_bal_file_by_content_and_says_its_cameras(tmp_path, rng, capsys):
    p = _problem(rng)
    path = _write("bal", tmp_path / "problem-6-80-pre", p, rng)  # no suffix, as BAL names them
    code = main(["reconstruct", str(path), "--out", str(tmp_path / "cloud.ply")])
    out = capsys.readouterr().out
    assert code == 0 and "radial camera" in out, out
    code = main(["reconstruct", str(path), "--out", str(tmp_path / "own.ply"), "--start", "own",
                 "--camera", "radial"])
    assert code == 0


def test_start_choices_are_checked(tmp_path, rng):
    p = _problem(rng)
    path = _write("bal", tmp_path / "problem.txt", p, rng)
    with pytest.raises(MpeError, match="not camera='perspective'; start='own'"):
        prepare(path, camera="perspective")
    with pytest.raises(MpeError, match="principal point at the image centre"):
        prepare(path, principal_point=(1.0, 2.0))
    with pytest.raises(MpeError, match="start: 'mine' is not one of"):
        prepare(path, start="mine")
    csv = tmp_path / "in.csv"
    csv.write_text("view,point,x,y\n" + "".join(f"{k},{i},{i + k},{i * i}\n"
                                                 for k in range(2) for i in range(5)))
    with pytest.raises(MpeError, match="start='file' needs cameras and points"):
        prepare(csv, start="file")


def _bal_text(p):
    lines = [f"{K} {N} {len(p['view'])}"]
    lines += [f"{k} {i} 1.5 2.5" for k, i in zip(p["view"], p["point"])]
    lines += ["0.01"] * (9 * K) + ["0.5"] * (3 * N)
    return "\n".join(lines) + "\n"


DAMAGED = [
    ("bal", lambda p: "3 4 5\n0 0 1 2\n", "the header declares 3 cameras, 4 points and 5 "
                                          "observations, 59 numbers in all, but the file has"),
    ("bal", lambda p: _bal_text(p).replace(" 2.5\n", " x2.5\n", 1), "after line 1: 'x2.5' is not a number"),
    ("bal", lambda p: _bal_text(p).rsplit("0.5\n", 1)[0], "numbers after line 1, but 6 cameras"),
    ("bal", lambda p: _bal_text(p).replace(" 2.5\n", " nan\n", 1), "a value is not finite"),
    ("bal", lambda p: _bal_text(p).replace("\n0 ", "\n9 ", 1), "camera index 9 is not one of 0..5"),
    ("bal", lambda p: f"{K} {N} 99999999999\n", "99999999999 observations"),
    ("bundler", lambda p: "# Bundle file v0.3\n2 0\n" + "1 " * 12 + " " * 60,
     "2 cameras need 30 numbers, the file has 12"),
    ("bundler", lambda p: "# Bundle file v0.3\n2 1\n", "2 cameras and 1 points, 37 numbers in all"),
    ("bundler", lambda p: "# Bundle file v0.3\n1 x\n", "line 2: expected 2 counts, got '1 x'"),
    ("bundler", lambda p: "# Bundle file v0.3\n1 1\n" + "1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n"
                          "0 0 0\n1 1 1\n3 0 0 1 1", "point 0 of 1: the file ends inside its view list"),
    ("bundler", lambda p: "# Bundle file v0.3\n1 1\n" + "1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n"
                          "0 0 0\n1 1 1\n1 4 0 1 1\n", "names camera 4, not one of 0..0"),
    ("bundler", lambda p: "# Bundle file v0.3\n2 3\n" + "1 0 0\n2 0 0\n0 1 0\n0 0 1\n0 0 0\n" * 2
                          + "".join("0 0 0\n1 1 1\n2 0 0 1 1 1 0 2 2\n" for _ in range(3)),
     "camera 0: its rotation is not a rotation matrix"),
]


@pytest.mark.parametrize("kind, text, message", DAMAGED)
def test_damaged_files_get_one_line(kind, text, message, tmp_path, rng, capsys):
    path = tmp_path / "damaged.out"
    path.write_text(text(_problem(rng)))
    code = main(["reconstruct", str(path), "--out", str(tmp_path / "cloud.ply")])
    err = capsys.readouterr().err
    assert code == 2, err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "cloud.ply").exists()


@pytest.mark.parametrize("kind, suffix", [("bundler", ".bal"), ("bal", ".out")])
def test_a_solution_written_as_bundler_or_bal_reads_back_as_solved(kind, suffix, tmp_path, rng, capsys):
    p = _problem(rng)
    source = _write(kind, tmp_path / "problem.txt", p, rng)
    out = tmp_path / f"solved{suffix}"
    assert main(["reconstruct", str(source), "--out", str(out)]) == 0
    solved = reconstruct(source)
    back = read_bundle_file(out)
    for k, view in enumerate(back):
        camera = view["start_camera"]
        assert camera["focal"] == pytest.approx(solved.cameras[k].focal_px, rel=1e-12)
        np.testing.assert_allclose(camera["distortion"], [solved.cameras[k].k1, solved.cameras[k].k2],
                                   rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(camera["rotation"], solved.cameras[k].rotation, atol=1e-12)
    # the written start is the solution: it reprojects onto the written keypoints exactly
    again = reconstruct(out)
    assert again.facts["reprojection_rms_px"] < 1e-6 and again.facts["iterations"] <= 2
    placed = ~np.isin(solved.ids, solved.unplaced)
    assert _similarity_error(again.points, solved.points[placed][again.ids]) < 1e-9


def test_a_pinhole_solution_of_keypoints_is_written_centred_on_its_principal_point(tmp_path, rng):
    p = _problem(rng)
    rows = [(v, i, float(x) + 400.0, float(y) + 300.0) for v, i, (x, y) in zip(p["view"], p["point"], p["xy"])]
    csv = tmp_path / "keypoints.csv"
    csv.write_text("view,point,x,y\n" + "\n".join(f"{v},{i},{x!r},{y!r}" for v, i, x, y in rows) + "\n")
    out = tmp_path / "solved.bal"
    assert main(["reconstruct", str(csv), "--out", str(out), "--camera", "radial",
                 "--principal-point", "400,300"]) == 0
    again = reconstruct(out)
    assert again.facts["reprojection_rms_px"] < 1e-4


@pytest.mark.parametrize("flags, says", [
    ([], "give --camera perspective or radial"),
    (["--camera", "scaled"], "--camera scaled may fit another"),
    (["--objective", "stress"], "holds fitted pinhole cameras"),
])
def test_a_solution_file_that_could_not_hold_the_fit_is_refused_before_the_solve(flags, says, tmp_path, rng,
                                                                                 capsys):
    p = _problem(rng)
    csv = tmp_path / "keypoints.csv"
    csv.write_text("view,point,x,y\n" + "\n".join(
        f"{v},{i},{float(x)!r},{float(y)!r}" for v, i, (x, y) in zip(p["view"], p["point"], p["xy"])) + "\n")
    assert main(["reconstruct", str(csv), "--out", str(tmp_path / "x.out"), *flags]) == 2
    assert says in capsys.readouterr().err and not (tmp_path / "x.out").exists()
