"""Photo folders as users have them (issue 60): non-image files ignored; grey,
16-bit and RGBA photos read; a truncated, empty or non-image file skipped with
a warning naming it; fewer than 2 usable photos refused in one line."""
import os

import numpy as np
import pytest
from PIL import Image
from scipy.ndimage import gaussian_filter

from mpe3d.errors import MpeError
from mpe3d.harness.userdata.photo_folder import IMAGE_DIR, list_photos, usable_photos

FOCAL_35MM = 0xA405  # EXIF FocalLengthIn35mmFilm, in the Exif sub-IFD 0x8769


def texture(height=30, width=40, channels=0, seed=0) -> np.ndarray:
    """Smoothed noise in [0, 1]: SIFT finds features in it."""
    shape = (height, width, channels) if channels else (height, width)
    sigma = (2, 2, 0) if channels else 2
    values = gaussian_filter(np.random.default_rng(seed).random(shape), sigma)
    return (values - values.min()) / np.ptp(values)


def eight_bit(values: np.ndarray) -> np.ndarray:
    return np.rint(values * 255).astype(np.uint8)


def photo(path, height=30, width=40, seed=0, **save):
    Image.fromarray(eight_bit(texture(height, width, 3, seed))).save(path, **save)
    return path


def truncated(path, seed=0):
    data = photo(path, seed=seed).read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def test_only_photos_are_listed_and_other_files_are_ignored_silently(tmp_path):
    for name in ("b.png", "a.jpg", "C.JPG", "d.tif", "e.webp"):
        photo(tmp_path / name)
    for name in ("notes.txt", ".DS_Store", "database.db", "cameras.txt", "IMG_1.CR2", "README"):
        (tmp_path / name).write_bytes(b"not a photo\n")
    photo(tmp_path / ".hidden.jpg")  # dot-files are hidden, even photos
    (tmp_path / "._a.jpg").write_bytes(b"\x00\x05\x16\x07 AppleDouble")  # macOS's resource fork of a.jpg
    (tmp_path / "sub.jpg").mkdir()
    photo(tmp_path / "sub.jpg" / "f.jpg")  # subfolders are not read
    assert list_photos(tmp_path) == ["C.JPG", "a.jpg", "b.png", "d.tif", "e.webp"]
    found = usable_photos(tmp_path, tmp_path / "scratch")
    assert found.names == ["C.JPG", "a.jpg", "b.png", "d.tif", "e.webp"] and found.skipped == []


@pytest.mark.parametrize("name", ["cut.jpg", "cut.png"])
def test_a_truncated_photo_is_skipped_with_a_warning_naming_it(tmp_path, name):
    photo(tmp_path / "a.jpg", seed=1)
    photo(tmp_path / "b.jpg", seed=2)
    truncated(tmp_path / name)
    found = usable_photos(tmp_path, tmp_path / "scratch")
    assert found.names == ["a.jpg", "b.jpg"] and name not in found.sizes
    (line,) = found.skipped
    assert line.startswith(f"{tmp_path / name}: skipped, truncated") and "\n" not in line


def test_an_empty_file_is_skipped_with_a_warning_naming_it(tmp_path):
    photo(tmp_path / "a.jpg", seed=1)
    photo(tmp_path / "b.jpg", seed=2)
    (tmp_path / "empty.jpg").write_bytes(b"")
    found = usable_photos(tmp_path, tmp_path / "scratch")
    assert found.names == ["a.jpg", "b.jpg"]
    assert found.skipped == [f"{tmp_path / 'empty.jpg'}: skipped, empty (0 bytes)"]


def test_a_text_file_named_jpg_is_skipped_with_a_warning_naming_it(tmp_path):
    photo(tmp_path / "a.jpg", seed=1)
    photo(tmp_path / "b.jpg", seed=2)
    (tmp_path / "notes.jpg").write_text("focal length 35 mm, tripod\n")
    found = usable_photos(tmp_path, tmp_path / "scratch")
    assert found.names == ["a.jpg", "b.jpg"]
    assert found.skipped == [f"{tmp_path / 'notes.jpg'}: skipped, not an image (a text file)"]


def test_grey_rgba_cmyk_palette_and_misnamed_photos_are_read_as_they_are(tmp_path):
    """COLMAP reads these itself: no copy, image_dir is the user's folder."""
    Image.fromarray(eight_bit(texture(seed=1))).save(tmp_path / "grey.jpg")
    rgba = np.dstack([eight_bit(texture(channels=3, seed=2)), np.full((30, 40), 128, np.uint8)])
    Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba.png")
    Image.fromarray(eight_bit(texture(channels=3, seed=3))).convert("CMYK").save(tmp_path / "cmyk.jpg")
    Image.fromarray(eight_bit(texture(channels=3, seed=4))).convert("P").save(tmp_path / "palette.png")
    photo(tmp_path / "png-inside.jpg", seed=5, format="PNG")
    photo(tmp_path / "tall.png", height=50, width=20, seed=6)
    found = usable_photos(tmp_path, tmp_path / "scratch")
    assert found.names == ["cmyk.jpg", "grey.jpg", "palette.png", "png-inside.jpg", "rgba.png", "tall.png"]
    assert found.image_dir == tmp_path and found.converted == [] and found.skipped == []
    assert found.sizes["tall.png"] == (20, 50) and found.sizes["grey.jpg"] == (40, 30)
    assert not (tmp_path / "scratch").exists()


def test_a_16_bit_png_gets_a_stretched_8_bit_copy_under_its_own_name(tmp_path):
    """12-bit data in a 16-bit PNG: COLMAP's division by 257 leaves it black."""
    values = np.rint(texture(seed=1) * 4095).astype(np.uint16)
    Image.fromarray(values).save(tmp_path / "deep.png")
    assert Image.open(tmp_path / "deep.png").mode == "I;16"
    exif = Image.Exif()
    exif[0x8769] = {FOCAL_35MM: 28}
    photo(tmp_path / "a.jpg", seed=2, exif=exif.tobytes())
    found = usable_photos(tmp_path, tmp_path / "scratch")
    image_dir = tmp_path / "scratch" / IMAGE_DIR
    assert found.names == ["a.jpg", "deep.png"] and found.converted == ["deep.png"]
    assert found.image_dir == image_dir and found.sizes["deep.png"] == (40, 30)
    with Image.open(image_dir / "deep.png") as copy:
        assert copy.format == "PNG" and copy.mode == "L" and copy.size == (40, 30)
        pixels = np.asarray(copy)
    assert pixels.max() == 255 and np.corrcoef(pixels.ravel(), values.ravel())[0, 1] > 0.99
    # the photo COLMAP reads as it is: a link to the user's file, its EXIF with it
    assert (image_dir / "a.jpg").is_symlink() and os.path.samefile(image_dir / "a.jpg", tmp_path / "a.jpg")
    assert Image.open(image_dir / "a.jpg").getexif().get_ifd(0x8769)[FOCAL_35MM] == 28


def test_a_webp_gets_an_8_bit_copy_that_keeps_its_exif(tmp_path):
    exif = Image.Exif()
    exif[0x010F], exif[0x0110], exif[0x8769] = "Pixel", "7", {FOCAL_35MM: 24}
    photo(tmp_path / "a.webp", seed=1, exif=exif.tobytes(), lossless=True)
    photo(tmp_path / "b.jpg", seed=2)
    found = usable_photos(tmp_path, tmp_path / "scratch")
    assert found.names == ["a.webp", "b.jpg"] and found.converted == ["a.webp"]
    with Image.open(found.image_dir / "a.webp") as copy:
        assert copy.format == "PNG" and copy.mode == "RGB"
        kept = copy.getexif()
    assert kept[0x010F] == "Pixel" and kept.get_ifd(0x8769)[FOCAL_35MM] == 24


def test_fewer_than_two_usable_photos_is_one_line_naming_the_folder(tmp_path):
    photo(tmp_path / "a.jpg")
    truncated(tmp_path / "b.jpg")
    (tmp_path / "c.png").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("ignored")
    with pytest.raises(MpeError) as caught:
        usable_photos(tmp_path, tmp_path / "scratch")
    message = str(caught.value)
    assert message.startswith(f"{tmp_path}: 1 usable photo(s) of 3, 2 skipped (b.jpg: truncated; c.png: empty")
    assert "\n" not in message and "needs 2" in message


def test_a_folder_of_raw_files_says_so_in_one_line(tmp_path):
    for name in ("IMG_1.CR2", "IMG_2.CR2", "notes.txt"):
        (tmp_path / name).write_bytes(b"II*\x00raw")
    with pytest.raises(MpeError, match=r"no photos \(.*raw camera file\(s\) \(IMG_1.CR2, ...\)") as caught:
        usable_photos(tmp_path, tmp_path / "scratch")
    assert str(caught.value).startswith(f"{tmp_path}: ") and "\n" not in str(caught.value)
    with pytest.raises(MpeError, match="no such folder"):
        list_photos(tmp_path / "missing")


def test_colmap_extracts_sift_from_every_usable_photo(tmp_path):
    """End to end: the copies and links in image_dir are what COLMAP reads,
    grey, 16-bit (12-bit data), RGBA, CMYK, WebP (its EXIF focal length too);
    the truncated photo is not given to it."""
    pycolmap = pytest.importorskip("pycolmap")
    folder = tmp_path / "photos"
    folder.mkdir()
    size = 200
    Image.fromarray(eight_bit(texture(size, size, seed=1))).save(folder / "grey.png")
    Image.fromarray(np.rint(texture(size, size, seed=2) * 4095).astype(np.uint16)).save(folder / "deep.png")
    Image.fromarray(np.rint(texture(size, size, seed=3) * 65535).astype(np.uint16)).save(folder / "deep.tif")
    rgba = np.dstack([eight_bit(texture(size, size, 3, seed=4)), np.full((size, size), 255, np.uint8)])
    Image.fromarray(rgba, "RGBA").save(folder / "rgba.png")
    Image.fromarray(eight_bit(texture(size, size, 3, seed=5))).convert("CMYK").save(folder / "cmyk.jpg")
    exif = Image.Exif()
    exif[0x8769] = {FOCAL_35MM: 50}
    photo(folder / "phone.webp", size, size, seed=6, exif=exif.tobytes(), lossless=True)
    truncated(folder / "cut.jpg")
    found = usable_photos(folder, tmp_path / "scratch")
    assert found.converted == ["deep.png", "deep.tif", "phone.webp"]
    assert [line.split(":")[0] for line in found.skipped] == [str(folder / "cut.jpg")]

    database = tmp_path / "database.db"
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = 1
    pycolmap.extract_features(database, found.image_dir, image_names=found.names, extraction_options=options,
                              device=pycolmap.Device.cpu)
    with pycolmap.Database.open(str(database)) as db:
        images = {image.name: image for image in db.read_all_images()}
        keypoints = {name: db.num_keypoints_for_image(image.image_id) for name, image in images.items()}
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
    assert sorted(keypoints) == found.names
    assert all(count > 100 for count in keypoints.values()), keypoints
    phone = cameras[images["phone.webp"].camera_id]
    assert (phone.width, phone.height) == found.sizes["phone.webp"]
    assert phone.has_prior_focal_length
    assert phone.focal_length == pytest.approx(50 / 43.27 * np.hypot(size, size))  # COLMAP's 35-mm rule


def test_a_folder_of_raw_files_is_that_one_line_on_the_command_line(tmp_path, capsys):
    from mpe3d.cli import main

    for name in ("IMG_1.CR2", "IMG_2.CR2"):
        (tmp_path / name).write_bytes(b"II*\x00raw")
    assert main(["reconstruct", str(tmp_path), "--out", str(tmp_path / "c.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "2 raw camera file(s) (IMG_1.CR2, ...) are not read: export them" in err


def test_a_photo_past_pils_pixel_guard_is_read(tmp_path, monkeypatch):
    """PIL refuses images of more than twice its MAX_IMAGE_PIXELS (179 MP, under a
    phone's 200-MP mode), which COLMAP reads: skipped as unreadable before. Its
    guard, lowered here to stand for such a photo, is lifted while decoding."""
    for name in ("a.png", "b.png"):
        Image.fromarray(np.full((64, 64), 128, dtype=np.uint8)).save(tmp_path / name)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)
    found = usable_photos(tmp_path, tmp_path / "scratch")
    assert found.names == ["a.png", "b.png"] and not found.skipped
    assert Image.MAX_IMAGE_PIXELS == 1000  # the guard is PIL's again afterwards
