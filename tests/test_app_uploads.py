"""``app/uploads.py``: zip limits and path confinement (no Streamlit needed)."""

from __future__ import annotations

import io
import os
import stat
import time
import zipfile

import pytest

from app import uploads
from artclass_core import InputError


# -- uploads.py: zip limits and path confinement -------------------------------------------------------------
def _zip(entries: dict[str, bytes], *, symlinks: dict[str, str] | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
        for name, target in (symlinks or {}).items():
            info = zipfile.ZipInfo(name)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            zf.writestr(info, target)
    return buf.getvalue()


def test_extract_zip_extracts_inside_the_folder(tmp_path):
    dest = uploads.extract_zip(_zip({"seq/meta.json": b"{}", "seq/rgb/0.png": b"x" * 10}), tmp_path / "out")
    assert (dest / "seq" / "meta.json").read_bytes() == b"{}"
    assert (dest / "seq" / "rgb" / "0.png").stat().st_size == 10


@pytest.mark.parametrize(
    "entries, symlinks, problem",
    [
        ({"../evil.txt": b"x"}, None, "points outside the folder"),
        ({"seq/../../evil.txt": b"x"}, None, "points outside the folder"),
        ({"/etc/evil.txt": b"x"}, None, "absolute path"),
        ({"C:/evil.txt": b"x"}, None, "absolute path"),
        ({"..\\evil.txt": b"x"}, None, "points outside the folder"),
        ({"ok.txt": b"x"}, {"seq/link": "/etc/passwd"}, "symbolic link"),
    ],
)
def test_extract_zip_refuses_escaping_entries(tmp_path, entries, symlinks, problem):
    with pytest.raises(InputError, match=problem) as err:
        uploads.extract_zip(_zip(entries, symlinks=symlinks), tmp_path / "out", name="upload.zip")
    assert err.value.path == "upload.zip"
    assert not (tmp_path / "out").exists()
    assert not (tmp_path / "evil.txt").exists()


def test_extract_zip_limits(tmp_path):
    many = _zip({f"f{i}.txt": b"x" for i in range(11)})
    with pytest.raises(InputError, match="holds 11 entries; the limit is 10"):
        uploads.extract_zip(many, tmp_path / "a", max_files=10)
    big = _zip({"big.bin": b"\0" * 2_000_000})  # compresses to a few kB
    assert len(big) < 50_000
    with pytest.raises(InputError, match="the limit is 1.0 MB"):
        uploads.extract_zip(big, tmp_path / "b", max_total_bytes=1_000_000)
    with pytest.raises(InputError, match="not a readable zip file"):
        uploads.extract_zip(b"PK\x03\x04 truncated", tmp_path / "c")
    assert not any((tmp_path / d).exists() for d in "abc")
    uploads.extract_zip(many, tmp_path / "d", max_files=11)  # at the limit: fine
    assert len(list((tmp_path / "d").iterdir())) == 11


def test_extract_upload_is_content_addressed_and_pruned(tmp_path):
    data = _zip({"seq/meta.json": b"{}"})
    first = uploads.extract_upload(data, name="a.zip", root=tmp_path)
    again = uploads.extract_upload(data, name="b.zip", root=tmp_path)
    assert first == again and (first / "seq" / "meta.json").is_file()
    other = uploads.extract_upload(_zip({"x.txt": b"1"}), name="c.zip", root=tmp_path)
    assert other != first
    old = time.time() - 3 * 24 * 3600
    os.utime(first, (old, old))
    assert uploads.prune(tmp_path, max_age_s=24 * 3600) == [first]
    assert not first.exists() and other.exists()


def test_confine(tmp_path):
    root = tmp_path / "root"
    (root / "seq").mkdir(parents=True)
    (tmp_path / "outside").mkdir()
    (root / "escape").symlink_to(tmp_path / "outside")
    assert uploads.confine(str(root / "seq"), [root]) == str((root / "seq").resolve())
    assert uploads.confine("seq", [root]) == str((root / "seq").resolve())
    assert uploads.confine(f"{root}/seq#obj_1", [root]) == f"{(root / 'seq').resolve()}#obj_1"
    for bad in (str(tmp_path / "outside"), f"{root}/../outside", "../outside", str(root / "escape"), "/"):
        with pytest.raises(InputError, match="outside the data folders"):
            uploads.confine(bad, [root])
    with pytest.raises(InputError, match="no folder given"):
        uploads.confine("  ", [root])
    with pytest.raises(InputError, match="no data folders are configured"):
        uploads.confine(str(root), [])


def test_data_roots(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert uploads.data_roots(["--data-root", str(a), "-x", "--data-root", str(b)], {}) == [a, b]
    assert uploads.data_roots([], {"ARTCLASS_DATA_ROOTS": f"{a}{os.pathsep}{b}"}) == [a, b]
    assert uploads.data_roots(["tests/test_app.py", "-q"], {}, default=[a]) == [a]
    assert uploads.data_roots(["--data-root", str(a)], {"ARTCLASS_DATA_ROOTS": str(b)}) == [a, b]
