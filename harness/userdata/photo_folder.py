"""A folder of photos as users have them: which files are photos, which of
them can be read, and 8-bit copies of those COLMAP cannot read as they are.

* :func:`list_photos`: the folder's files named as photos (not its subfolders,
  not hidden dot-files such as macOS's ``._IMG_0001.JPG``); everything else
  (``notes.txt``, ``.DS_Store``, ``database.db``, raw camera files) is ignored
  silently;
* :func:`usable_photos`: each of them opened and fully decoded with PIL, by
  its content, not its name; an empty, truncated, unreadable or non-image file
  is skipped with one warning line naming it; photos COLMAP cannot read as they
  are get an 8-bit copy (same name, EXIF carried over) beside links to the
  others.

What COLMAP 4.2.1 reads (pycolmap 4.2.1's wheel, OpenImageIO 3.1; measured by
``pycolmap.extract_features`` on each kind of file): JPEG (baseline,
progressive, CMYK, with EXIF orientation left as stored), PNG (8 and 16 bits;
grey, grey+alpha, RGB, RGBA, palette, 1 bit), TIFF (8, 16 bits, float,
CMYK, LZW, JPEG-compressed), BMP, PNM and TGA, each by its content whatever
its name (alpha dropped, 16 bits divided by 257). It does not read WebP, GIF,
JPEG 2000, AVIF or HEIC: those are skipped without a word, as are empty and
text files. A truncated JPEG or PNG is read without a word too, its missing
rows grey, and its SIFT features extracted from what is left: hence the full
decode here. A 16-bit photo whose values fill only the low bits (12-bit data,
a dark exposure) comes out black after the division by 257 (0 SIFT features
on such a 200x200 texture, against 1,089 for the same texture at full range):
16-bit grey and float photos are therefore copied stretched to their 99.9th
percentile. PIL reads 16-bit RGB as 8 bits already (the high byte, as COLMAP
does), so those are left to COLMAP.

Decoding costs little beside SIFT: PIL decodes a 3072x2048 JPEG in 39 ms
(100 photos: 3.9 s, files in the page cache), COLMAP's SIFT takes 6 to 10 s
of it on one thread (8,192 features, a busy 2-core machine): under 1 %. A
cheaper check (the JPEG's end marker: 3 ms) would miss corrupt data that a
decode finds, and an 8-bit copy needs the decode anyway.
"""

from __future__ import annotations

import os
import shutil
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mpe3d.errors import MachineError, MpeError, first_line

# Read by COLMAP as they are (when PIL says their content is one of NATIVE_FORMATS).
NATIVE_SUFFIXES = (".jpg", ".jpeg", ".jpe", ".jfif", ".mpo", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm",
                   ".pbm", ".pnm", ".tga")
# Read by PIL, not by COLMAP: copied as 8-bit PNG (HEIC only with pillow-heif installed).
CONVERTED_SUFFIXES = (".webp", ".gif", ".jp2", ".j2k", ".jpf", ".jpx", ".avif", ".heic", ".heif")
PHOTO_SUFFIXES = NATIVE_SUFFIXES + CONVERTED_SUFFIXES
# Raw camera files: neither reader decodes them; named in the error when nothing else is usable.
RAW_SUFFIXES = (".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".dng", ".raf", ".orf", ".rw2",
                ".pef", ".srw", ".x3f", ".3fr", ".iiq", ".erf", ".kdc", ".mos", ".mrw", ".raw", ".rwl")
NATIVE_FORMATS = frozenset({"JPEG", "MPO", "PNG", "TIFF", "BMP", "PPM", "TGA"})  # PIL's format names
STRETCH_PERCENTILE = 99.9  # a deep photo's value that becomes 255 in its copy
IMAGE_DIR = "images"  # the folder in ``scratch`` that holds the copies and the links
# EXIF that a copy keeps: make, model, orientation, and the Exif and GPS sub-IFDs
# (focal lengths, focal-plane resolution, GPS position: what COLMAP reads).
EXIF_TAGS = (0x010F, 0x0110, 0x0112)
EXIF_IFDS = (0x8769, 0x8825)
SIGNATURES = ((b"\xff\xd8\xff", "JPEG"), (b"\x89PNG\r\n\x1a\n", "PNG"), (b"II*\x00", "TIFF"), (b"MM\x00*", "TIFF"),
              (b"BM", "BMP"), (b"RIFF", "WebP"), (b"GIF8", "GIF"), (b"\x00\x00\x00\x0cjP  ", "JPEG 2000"))
HEIF_BRANDS = (b"heic", b"heix", b"hevc", b"heim", b"heis", b"mif1", b"msf1")


@dataclass
class PhotoFolder:
    """The usable photos of a folder: give COLMAP ``image_dir`` and ``names``."""

    image_dir: Path  # the user's folder, or scratch/images (copies and links) when some photo needed a copy
    names: list[str]  # usable photos, by the user's names, sorted
    sizes: dict[str, tuple[int, int]]  # (width, height) of each, as stored (EXIF orientation not applied)
    skipped: list[str] = field(default_factory=list)  # one warning line per skipped file, naming it and why
    converted: list[str] = field(default_factory=list)  # names written as 8-bit copies in image_dir


def list_photos(folder: Path) -> list[str]:
    """The files of ``folder`` named as photos (:data:`PHOTO_SUFFIXES`, any
    case), sorted; not its subfolders nor hidden dot-files. Names only: what
    each holds is :func:`usable_photos`'s to find out."""
    return sorted(name for name in _entries(Path(folder)) if Path(name).suffix.lower() in PHOTO_SUFFIXES)


def raw_photos(folder: Path) -> list[str]:
    """The folder's raw camera files (not read: a user exports them as JPEG or TIFF)."""
    return [name for name in _entries(Path(folder)) if Path(name).suffix.lower() in RAW_SUFFIXES]


def usable_photos(folder: Path, scratch: Path) -> PhotoFolder:
    """The photos of ``folder`` that decode, each checked by its content
    (see the module's docstring); copies, when some are needed, and links to
    the others go to ``scratch/images``. Fewer than 2 usable photos: one line."""
    folder, scratch = Path(folder), Path(scratch)
    candidates = list_photos(folder)
    if (scratch / IMAGE_DIR).resolve() == folder.resolve():  # copies there would replace the user's photos
        raise MpeError(f"{scratch}: a scratch folder whose {IMAGE_DIR}/ is the photo folder {folder}")
    _register_heif()
    names, sizes, skipped, converted = [], {}, [], []
    for name in candidates:
        image = _decoded(folder / name)
        if isinstance(image, str):
            skipped.append((name, image))
            continue
        with image:
            if image.format not in NATIVE_FORMATS or _deep(image.mode):
                why = _write_copy(image, scratch / IMAGE_DIR / name)
                if why:
                    skipped.append((name, why))
                    continue
                converted.append(name)
            names.append(name)
            sizes[name] = image.size
    if len(names) < 2:
        raise MpeError(_too_few(folder, candidates, names, skipped))
    image_dir = folder
    if converted:
        image_dir = scratch / IMAGE_DIR
        copied = set(converted)
        for name in names:
            if name not in copied:
                _link(folder.absolute() / name, image_dir / name)
    return PhotoFolder(image_dir, names, sizes, [f"{folder / name}: skipped, {why}" for name, why in skipped],
                       converted)


def _entries(folder: Path) -> list[str]:
    """The names of ``folder``'s files (and links), hidden ones left out."""
    if not folder.is_dir():
        raise MpeError(f"{folder}: no such folder")
    try:
        with os.scandir(folder) as entries:
            return [e.name for e in entries if not e.name.startswith(".") and not e.is_dir()
                    and (e.is_file() or e.is_symlink())]
    except OSError as exc:
        raise MpeError(f"{folder}: cannot list the folder ({exc.strerror or first_line(exc)})") from None


def _register_heif() -> None:
    """HEIC/HEIF (iPhones' photos) through pillow-heif's PIL plugin, when it is installed."""
    try:
        from pillow_heif import register_heif_opener
    except ImportError:
        return
    register_heif_opener()


def _decoded(path: Path):
    """``path`` opened and fully decoded by PIL (``Image.load``: ``verify``
    misses a truncated image), or why not, as a few words."""
    from PIL import Image, UnidentifiedImageError

    try:
        if path.stat().st_size == 0:
            return "empty (0 bytes)"
    except OSError as exc:
        return f"unreadable ({exc.strerror or first_line(exc)})"
    image, limit = None, Image.MAX_IMAGE_PIXELS
    try:
        with warnings.catch_warnings():  # PIL's warnings on odd metadata, large images: not the user's business
            warnings.simplefilter("ignore")
            # no pixel limit: a phone's 200-MP photo is twice PIL's guard against decompression bombs
            Image.MAX_IMAGE_PIXELS = None
            image = Image.open(path)
            image.load()
        return image
    except UnidentifiedImageError:
        return _not_an_image(path)
    except Exception as exc:  # a broken file makes PIL raise anything (OSError, SyntaxError, ValueError, ...)
        if image is not None:
            image.close()
        return _why(exc)
    finally:
        Image.MAX_IMAGE_PIXELS = limit


def _why(exc: Exception) -> str:
    text = first_line(exc)
    if isinstance(exc, (OSError, EOFError)) and ("truncat" in text.lower() or isinstance(exc, EOFError)):
        return "truncated (the file ends before its image does: an interrupted copy or download?)"
    if isinstance(exc, OSError) and exc.strerror:
        return f"unreadable ({exc.strerror})"
    return f"unreadable ({type(exc).__name__}: {text})"


def _not_an_image(path: Path) -> str:
    """Why PIL cannot identify ``path``, from its first bytes."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(512)
    except OSError as exc:
        return f"unreadable ({exc.strerror or first_line(exc)})"
    if head[4:8] == b"ftyp" and head[8:12] in HEIF_BRANDS:
        return "a HEIC/HEIF photo, which needs pillow-heif to be read (pip install pillow-heif)"
    kind = next((name for magic, name in SIGNATURES if head.startswith(magic)), None)
    if kind:
        return f"truncated or corrupt (it starts as a {kind} file, but no image can be read from it)"
    try:
        if b"\x00" not in head:
            head.decode("utf-8")
            return "not an image (a text file)"
    except UnicodeDecodeError:
        pass
    return "not an image (no image format that PIL knows)"


def _deep(mode: str) -> bool:
    """PIL's modes of grey beyond 8 bits: I;16 (16-bit PNG, TIFF), I (32-bit), F (float)."""
    return mode == "F" or mode.startswith("I")


def _eight_bit(image):
    """``image`` as 8-bit grey or RGB: deep grey stretched linearly so that its
    99.9th percentile is 255 (a 16-bit photo of 12-bit data stays visible);
    alpha dropped, as COLMAP drops it."""
    from PIL import Image

    if _deep(image.mode):
        pixels = np.nan_to_num(np.asarray(image, dtype=np.float32))
        top = float(np.percentile(pixels[::4, ::4], STRETCH_PERCENTILE))
        top = top if top > 0 else float(pixels.max())
        scaled = np.clip(pixels * (255.0 / top), 0, 255) if top > 0 else np.zeros_like(pixels)
        return Image.fromarray(np.rint(scaled).astype(np.uint8))
    if image.mode in ("L", "RGB"):
        return image
    if image.mode in ("1", "LA", "La"):
        return image.convert("L")
    return image.convert("RGB")


def _exif(image) -> bytes | None:
    """The EXIF to carry over to ``image``'s copy: the file's own EXIF block
    when PIL kept it (JPEG, PNG, WebP, AVIF, HEIC), else (TIFF) the tags that
    matter (:data:`EXIF_TAGS`, :data:`EXIF_IFDS`) without the TIFF's layout."""
    from PIL import Image

    raw = image.info.get("exif")
    if isinstance(raw, bytes) and raw:
        return raw
    source, kept = image.getexif(), Image.Exif()
    for tag in EXIF_TAGS:
        if tag in source:
            kept[tag] = source[tag]
    for tag in EXIF_IFDS:
        ifd = source.get_ifd(tag)
        if ifd:
            kept[tag] = dict(ifd)
    return kept.tobytes() if len(kept) else None


def _write_copy(image, target: Path) -> str | None:
    """An 8-bit PNG of ``image`` at ``target`` (the photo's own name, PNG
    inside: COLMAP reads by content), EXIF carried over; None, or why the
    photo cannot be copied."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            copy = _eight_bit(image)
            try:
                exif = _exif(image)
            except Exception:  # a malformed EXIF block: the copy goes without it
                exif = None
    except Exception as exc:  # a mode PIL cannot convert (LAB, HSV, ...)
        return f"unreadable (its {image.mode} pixels cannot be converted to 8-bit RGB: {first_line(exc)})"
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        target.unlink(missing_ok=True)
        try:
            copy.save(target, format="PNG", compress_level=1, **({"exif": exif} if exif else {}))
        except OSError:
            raise
        except Exception:  # EXIF that PIL cannot write back: the copy goes without it
            copy.save(target, format="PNG", compress_level=1)
    except OSError as exc:
        if exc.errno is None:  # PIL's encoder, not the disk: this photo alone
            return f"unreadable (it cannot be written as an 8-bit PNG: {first_line(exc)})"
        raise MachineError(f"{target}: cannot write an 8-bit copy of the photo "
                           f"({exc.strerror or first_line(exc)})") from None
    return None


def _link(source: Path, target: Path) -> None:
    """``target`` showing ``source``'s file: a link (its EXIF is the file's), a copy where links fail."""
    try:
        target.unlink(missing_ok=True)
        try:
            os.symlink(source, target)
        except OSError:
            shutil.copy2(source, target)
    except OSError as exc:
        raise MachineError(f"{target}: cannot link or copy the photo there ({exc.strerror or first_line(exc)})") \
            from None


def _too_few(folder: Path, candidates: list[str], names: list[str], skipped: list[tuple[str, str]]) -> str:
    """One line: the folder, what it held, what was skipped and why."""
    raw = raw_photos(folder)
    raw_note = (f"; its {len(raw)} raw camera file(s) ({raw[0]}, ...) are not read: export them as JPEG or TIFF"
                if raw else "")
    if not candidates:
        return (f"{folder}: no photos ({', '.join(PHOTO_SUFFIXES[:8])}, ...){raw_note}; "
                "reconstruction needs 2 or more")
    listed = "; ".join(f"{name}: {why.split(' (')[0]}" for name, why in skipped)
    listed = f" ({listed if len(listed) <= 200 else listed[:197] + '...'})" if skipped else ""
    return (f"{folder}: {len(names)} usable photo(s) of {len(candidates)}, {len(skipped)} skipped{listed}"
            f"{raw_note}; reconstruction needs 2 or more")
