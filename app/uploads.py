"""Safe inputs for a shared server: zip uploads and typed-in folder paths. No Streamlit here.

Two rules keep a classroom server safe:

- A typed-in folder must lie inside one of the configured *data roots*
  (``--data-root DIR`` after ``--`` on the ``streamlit run`` line, repeatable, or the environment
  variable ``ARTCLASS_DATA_ROOTS``, ``os.pathsep``-separated; the bundled samples by default).
  Symbolic links are resolved before the check, so a link cannot lead out of a root.
- An uploaded zip is extracted into a fresh folder of its own, with limits on the number of entries
  and the total uncompressed size (counted while decompressing, not taken from the zip's headers),
  and no entry may escape that folder: absolute names, ``..`` components, symbolic links and
  encrypted entries are refused. The input is never written to; failures remove the partial folder.

Every refusal is an :class:`artclass_core.InputError` with a one-line message naming the file.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import os
import re
import shutil
import stat
import tempfile
import time
import zipfile
import zlib
from collections.abc import Iterable, Mapping
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from artclass_core import InputError

ENV_DATA_ROOTS = "ARTCLASS_DATA_ROOTS"
ENV_UPLOAD_DIR = "ARTCLASS_UPLOAD_DIR"
MAX_TOTAL_BYTES = 1 << 30  # 1 GiB uncompressed
MAX_FILES = 20_000
UPLOAD_MAX_AGE_S = 24 * 3600  # extracted uploads older than this are removed
_CHUNK = 1 << 20
_DRIVE = re.compile(r"^[A-Za-z]:")


def data_roots(
    argv: Iterable[str] | None = None,
    environ: Mapping[str, str] | None = None,
    *,
    default: Iterable[str | Path] = (),
) -> list[Path]:
    """The folders a typed-in path may lie in.

    Parameters
    ----------
    argv : the script's arguments (``sys.argv[1:]``); ``--data-root DIR`` may be repeated. Other
        arguments are ignored (the app also runs under pytest, whose arguments are not ours).
    environ : the environment; ``ARTCLASS_DATA_ROOTS`` holds ``os.pathsep``-separated folders
    default : the roots when neither gives any (the bundled samples)

    Returns
    -------
    list of absolute, resolved paths, in the order given, without duplicates
    """
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--data-root", action="append", default=[])
    known, _ = parser.parse_known_args(list(argv or []))
    environ = os.environ if environ is None else environ
    items = list(known.data_root) + [
        p for p in environ.get(ENV_DATA_ROOTS, "").split(os.pathsep) if p.strip()
    ]
    if not items:
        items = list(default)
    out: list[Path] = []
    for item in items:
        p = Path(item).expanduser().resolve()
        if p not in out:
            out.append(p)
    return out


def confine(text: str, roots: Iterable[Path]) -> str:
    """Resolve a typed-in path and check that it lies inside one of ``roots``.

    A relative path is taken relative to the first root that holds it (else the first root).
    A ``PATH#NAME`` suffix (one sequence of several, as :func:`artclass_core.open_sequences` reads
    it) is kept.

    Returns
    -------
    str : the resolved absolute path, with its ``#NAME`` suffix if any

    Raises
    ------
    InputError : empty input, no roots configured, or a path outside every root
    """
    roots = [Path(r).resolve() for r in roots]
    text = (text or "").strip()
    if not text:
        raise InputError("no folder given")
    if not roots:
        raise InputError(
            "no data folders are configured on this server (set ARTCLASS_DATA_ROOTS or --data-root)",
            path=text,
        )
    path_text, sep, name = text.partition("#") if "#" in text and not Path(text).exists() else (text, "", "")
    path = Path(path_text).expanduser()
    if not path.is_absolute():
        path = next((r / path for r in roots if (r / path).exists()), roots[0] / path)
    resolved = path.resolve()
    if not any(resolved == r or resolved.is_relative_to(r) for r in roots):
        allowed = ", ".join(str(r) for r in roots)
        raise InputError(f"outside the data folders this server allows ({allowed})", path=path_text)
    return str(resolved) + (f"#{name}" if sep else "")


def _entry_parts(info: zipfile.ZipInfo, *, zip_name: str) -> tuple[str, ...]:
    """The safe path components of a zip entry, or an InputError saying why it is refused."""
    name = info.filename.replace("\\", "/")
    if name.startswith("/") or _DRIVE.match(name):
        raise InputError(f"entry {info.filename!r} has an absolute path", path=zip_name)
    parts = tuple(p for p in PurePosixPath(name).parts if p not in ("", "."))
    if ".." in parts:
        raise InputError(f"entry {info.filename!r} points outside the folder ('..')", path=zip_name)
    if "\x00" in name:
        raise InputError(f"entry {info.filename!r} has a NUL character in its name", path=zip_name)
    if stat.S_ISLNK(info.external_attr >> 16):
        raise InputError(f"entry {info.filename!r} is a symbolic link (not allowed)", path=zip_name)
    if info.flag_bits & 0x1:
        raise InputError(f"entry {info.filename!r} is encrypted", path=zip_name)
    return parts


def extract_zip(
    source: bytes | BinaryIO | str | Path,
    dest: str | Path,
    *,
    max_total_bytes: int = MAX_TOTAL_BYTES,
    max_files: int = MAX_FILES,
    name: str | None = None,
) -> Path:
    """Extract a zip into ``dest`` (which must not exist yet), within limits.

    Parameters
    ----------
    source : the zip's bytes, an open binary file, or its path
    dest : the folder to create and fill
    max_total_bytes : limit on the total uncompressed size, counted while decompressing
    max_files : limit on the number of entries (files and folders)
    name : the file name shown in error messages (default: the path, or ``upload.zip``)

    Returns
    -------
    Path : ``dest``

    Raises
    ------
    InputError : not a zip, corrupt, too many entries, too large, or an entry that would escape
        ``dest`` (absolute path, ``..``, symbolic link) or is encrypted. ``dest`` is removed again.
    """
    zip_name = name or (str(source) if isinstance(source, (str, Path)) else "upload.zip")
    dest = Path(dest)
    if isinstance(source, (bytes, bytearray)):
        source = io.BytesIO(source)
    try:
        zf = zipfile.ZipFile(source)
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise InputError(f"not a readable zip file ({exc})", path=zip_name) from None
    with zf:
        infos = zf.infolist()
        if len(infos) > max_files:
            raise InputError(f"holds {len(infos)} entries; the limit is {max_files}", path=zip_name)
        declared = sum(i.file_size for i in infos)
        if declared > max_total_bytes:
            raise InputError(
                f"unpacks to {declared / 1e6:.1f} MB; the limit is {max_total_bytes / 1e6:.1f} MB",
                path=zip_name,
            )
        plan = [(info, _entry_parts(info, zip_name=zip_name)) for info in infos]
        dest.mkdir(parents=True, exist_ok=False)
        root = dest.resolve()
        try:
            written = 0
            for info, parts in plan:
                if not parts:
                    continue
                target = root.joinpath(*parts)
                if not target.resolve().is_relative_to(root):  # belt and braces
                    raise InputError(f"entry {info.filename!r} points outside the folder", path=zip_name)
                if info.is_dir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                with zf.open(info) as src, open(target, "xb") as out:
                    while chunk := src.read(_CHUNK):
                        written += len(chunk)
                        if written > max_total_bytes:
                            raise InputError(
                                f"unpacks to more than {max_total_bytes / 1e6:.1f} MB (the limit)",
                                path=zip_name,
                            )
                        out.write(chunk)
        except InputError:
            shutil.rmtree(dest, ignore_errors=True)
            raise
        except FileExistsError as exc:
            shutil.rmtree(dest, ignore_errors=True)
            raise InputError(f"entry {Path(exc.filename).name!r} appears twice", path=zip_name) from None
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, RuntimeError) as exc:
            shutil.rmtree(dest, ignore_errors=True)
            raise InputError(f"corrupt zip ({exc})", path=zip_name) from None
    return dest


def upload_root(environ: Mapping[str, str] | None = None) -> Path:
    """Where uploads are extracted: ``ARTCLASS_UPLOAD_DIR``, else ``<tmp>/artclass_uploads``."""
    environ = os.environ if environ is None else environ
    return Path(environ.get(ENV_UPLOAD_DIR) or Path(tempfile.gettempdir()) / "artclass_uploads")


def extract_upload(
    data: bytes,
    *,
    name: str,
    root: str | Path,
    max_total_bytes: int = MAX_TOTAL_BYTES,
    max_files: int = MAX_FILES,
    max_age_s: float = UPLOAD_MAX_AGE_S,
) -> Path:
    """Extract an uploaded zip into a folder named by its content's hash under ``root``.

    The same upload gives the same folder (so the app's caches, keyed on the path, are reused);
    extraction goes to a temporary sibling that is renamed when complete, so a half-extracted folder
    is never used. Extracted uploads older than ``max_age_s`` are removed first.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    prune(root, max_age_s=max_age_s)
    digest = hashlib.sha256(data).hexdigest()[:24]
    final = root / digest
    if final.is_dir():
        os.utime(final)  # keep it alive
        return final
    partial = root / f".partial-{digest}-{os.getpid()}-{time.monotonic_ns()}"
    extract_zip(data, partial, max_total_bytes=max_total_bytes, max_files=max_files, name=name)
    try:
        partial.rename(final)
    except OSError:  # another session extracted the same upload meanwhile
        shutil.rmtree(partial, ignore_errors=True)
    return final


def prune(root: str | Path, *, max_age_s: float) -> list[Path]:
    """Remove the extracted uploads under ``root`` last used more than ``max_age_s`` ago."""
    removed = []
    now = time.time()
    root = Path(root)
    if not root.is_dir():
        return removed
    for child in root.iterdir():
        try:
            if child.is_dir() and not child.is_symlink() and now - child.stat().st_mtime > max_age_s:
                shutil.rmtree(child, ignore_errors=True)
                removed.append(child)
        except OSError:
            continue
    return removed
