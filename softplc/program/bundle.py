"""Program bundles: a program with its io image and subnets in one zip archive.

Owns: the bundle format (docs/programs.md, "Program bundles"): a zip holding the files at
their paths relative to the bundle root and a manifest `softplc-bundle.json`
(`{"format": 1, "program": "deep/sub/c.yaml"}`); finding the files a program needs (its
`io_image:` and its subnets, recursively); the limits (size, count, path) and the path rule
(relative, `/`-separated, no `..`, nothing leaving the bundle); unpacking into a directory.
Does not know: compiling, HTTP, the scan.

Files are kept byte for byte: `softplc upload` gives back exactly what `softplc download`
packed. The archive is deterministic (fixed timestamps, sorted names): the same files make
the same bytes.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import tempfile
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Final

from softplc.core.errors import SoftplcError
from softplc.core.problems import Problem, ProgramError
from softplc.program.yamlload import load_yaml

MANIFEST: Final = "softplc-bundle.json"
FORMAT: Final = 1
MAX_FILES: Final = 64
MAX_FILE_BYTES: Final = 1 << 20  # one unpacked file
MAX_TOTAL_BYTES: Final = 4 << 20  # all unpacked files (the API's body limit is 1 MiB packed)
MAX_PATH_CHARS: Final = 200
MAX_DEPTH: Final = 8  # folders in one path
CONTENT_TYPE: Final = "application/zip"
_EPOCH: Final = (1980, 1, 1, 0, 0, 0)  # zip's earliest date: deterministic archives


class BundleError(SoftplcError, ValueError):
    """A bundle that cannot be used: the message says what is wrong and what was expected."""


@dataclass(frozen=True, slots=True)
class Bundle:
    """`program` is the path (inside the bundle) of the program file; `files` maps every
    path to its bytes."""

    program: str
    files: Mapping[str, bytes]

    @property
    def digest(self) -> str:
        """sha256 over names and contents: names the unpacked directory."""
        sha = hashlib.sha256(self.program.encode())
        for name in sorted(self.files):
            sha.update(b"\0" + name.encode() + b"\0" + self.files[name])
        return sha.hexdigest()


def is_bundle(blob: bytes) -> bool:
    return blob[:4] == b"PK\x03\x04"


# -- building from local files --------------------------------------------------------------

def referenced(program: str | Path) -> list[Path]:
    """The program file and every file it needs (io image, subnets, recursively), resolved.
    Files that cannot be read or parsed are left out: `check` reports them."""
    return [path for path in _walk(program) if path.is_file()]


def missing(program: str | Path) -> list[Path]:
    """Files the program references that are not there locally."""
    return [path for path in _walk(program) if not path.is_file()]


def file_of(program: str | Path) -> str:
    """The file of a program name: `FILE.xml#POU` names one SFC POU of FILE.xml (sfc.md)."""
    name, _, _ = str(program).partition("#")
    return name if name.lower().endswith(".xml") else str(program)


def _walk(program: str | Path) -> list[Path]:
    seen: list[Path] = []
    pending = [Path(file_of(program)).resolve()]
    while pending:
        path = pending.pop()
        if path in seen:
            continue
        seen.append(path)
        if path.suffix.lower() == ".xml" and path.with_suffix(".io.yml").is_file():
            pending.append(path.with_suffix(".io.yml"))  # an SFC chart's drivers: docs/sfc.md
        try:
            data, _ = load_yaml(path.read_text(encoding="utf-8"), str(path))
        except (OSError, UnicodeDecodeError):
            continue
        pending.extend(_references(data, path.parent))
    return seen


def _references(data: Any, base: Path) -> list[Path]:
    if not isinstance(data, Mapping):
        return []
    refs: list[Path] = []
    io_image = data.get("io_image")
    if isinstance(io_image, str) and io_image and "\0" not in io_image:
        refs.append((base / io_image).resolve())
    subnets = data.get("subnets")
    if isinstance(subnets, Mapping):
        for instance in subnets.values():
            net = instance.get("net") if isinstance(instance, Mapping) else None
            if isinstance(net, str) and net and "\0" not in net:
                refs.append((base / net).resolve())
    return refs


def from_files(program: str | Path) -> Bundle:
    """The bundle of a local program: its root is the deepest folder holding every file."""
    paths = referenced(program)
    root = Path(os.path.commonpath([p.parent for p in paths]))
    files: dict[str, bytes] = {}
    for path in paths:
        try:
            files[path.relative_to(root).as_posix()] = path.read_bytes()
        except OSError as exc:
            raise BundleError(f"{path}: cannot read: {exc.strerror}") from None
    pou = str(program)[len(file_of(program)):]  # "#POU" of a chart, kept in the manifest
    bundle = Bundle(paths[0].relative_to(root).as_posix() + pou, files)
    _check(bundle)
    return bundle


# -- the archive ----------------------------------------------------------------------------

def pack(bundle: Bundle) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        manifest = json.dumps({"format": FORMAT, "program": bundle.program}, sort_keys=True)
        for name, data in [(MANIFEST, manifest.encode()), *sorted(bundle.files.items())]:
            info = zipfile.ZipInfo(name, _EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            archive.writestr(info, data)
    return out.getvalue()


def unpack(blob: bytes, what: str = "bundle") -> Bundle:
    """Read and check an archive; BundleError (naming `what`) for anything out of bounds."""
    try:
        archive = zipfile.ZipFile(io.BytesIO(blob))
    except zipfile.BadZipFile as exc:
        raise BundleError(f"{what}: not a zip archive ({exc})") from None
    with archive:
        infos = [i for i in archive.infolist() if not i.is_dir()]
        if len(infos) > MAX_FILES + 1:
            raise BundleError(f"{what}: {len(infos) - 1} files, at most {MAX_FILES} expected")
        total = sum(i.file_size for i in infos)
        if total > MAX_TOTAL_BYTES:  # checked on the declared sizes, then on what is read
            raise BundleError(f"{what}: {total} bytes unpacked, at most {MAX_TOTAL_BYTES}")
        files: dict[str, bytes] = {}
        for info in infos:
            if info.filename in files:
                raise BundleError(f"{what}: {info.filename!r} appears twice")
            files[info.filename] = _read(archive, info, what)
    manifest = files.pop(MANIFEST, None)
    if manifest is None:
        raise BundleError(f"{what}: no {MANIFEST} (expected {{\"format\": 1, \"program\": "
                          "\"path/of/program.yaml\"}})")
    try:
        meta = json.loads(manifest)
        program = meta["program"]
        if meta.get("format") != FORMAT or not isinstance(program, str):
            raise ValueError(f"format {meta.get('format')!r}, expected {FORMAT}")
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise BundleError(f"{what}: {MANIFEST} unusable ({exc}); expected "
                          '{"format": 1, "program": "path/of/program.yaml"}') from None
    bundle = Bundle(program, files)
    _check(bundle, what)
    return bundle


def _read(archive: zipfile.ZipFile, info: zipfile.ZipInfo, what: str) -> bytes:
    limit = MAX_FILE_BYTES + 1 if info.filename != MANIFEST else 4096
    try:
        with archive.open(info) as member:
            data = member.read(limit)  # bounded: the declared size may lie
    except (zipfile.BadZipFile, NotImplementedError, RuntimeError, OSError) as exc:
        raise BundleError(f"{what}: {info.filename!r} cannot be read ({exc})") from None
    if len(data) >= limit:
        raise BundleError(f"{what}: {info.filename!r} is larger than {limit - 1} bytes")
    return data


def _check(bundle: Bundle, what: str = "bundle") -> None:
    for name in bundle.files:
        if why := path_problem(name):
            raise BundleError(f"{what}: {name!r}: {why}")
    if len(bundle.files) > MAX_FILES:
        raise BundleError(f"{what}: {len(bundle.files)} files, at most {MAX_FILES} expected")
    folders = {str(p) for name in bundle.files for p in PurePosixPath(name).parents}
    for name in sorted(bundle.files):
        if name in folders:  # `io` and `io/p.yaml` cannot both be unpacked
            inner = min(n for n in bundle.files if n.startswith(name + "/"))
            raise BundleError(f"{what}: {name!r} is a file and also the folder of {inner!r}")
    if sum(len(d) for d in bundle.files.values()) > MAX_TOTAL_BYTES:
        raise BundleError(f"{what}: more than {MAX_TOTAL_BYTES} bytes unpacked")
    if file_of(bundle.program) not in bundle.files:
        raise BundleError(f"{what}: the manifest's program {bundle.program!r} is not in the "
                          f"bundle (it holds {', '.join(sorted(bundle.files)) or 'nothing'})")


def path_problem(name: str) -> str | None:
    """Why `name` may not be a path in a bundle, None when it may."""
    if not name or len(name) > MAX_PATH_CHARS:
        return f"a path must have 1 to {MAX_PATH_CHARS} characters"
    if "\\" in name or "\0" in name or ":" in name:
        return "a path uses '/' and no '\\', ':' or NUL"
    path = PurePosixPath(name)
    if path.is_absolute() or any(part in ("", ".", "..") for part in name.split("/")):
        return "a path must be relative, without '.', '..' or empty parts (none may leave " \
               "the bundle)"
    if len(path.parts) > MAX_DEPTH + 1:
        return f"at most {MAX_DEPTH} folders deep"
    return None


def extract(bundle: Bundle, directory: str | Path) -> Path:
    """Unpack into `directory` (created atomically: a crash leaves it whole or absent);
    returns the program's path. An existing directory of the same digest is reused. A bundle
    that cannot be written (a full disk) is a ProgramError, the download refused."""
    try:
        return _extract(bundle, directory)
    except OSError as exc:
        raise ProgramError([Problem("bundle", 0, "", f"bundle: cannot be unpacked on the "
                                    f"server: {exc.strerror or exc}")]) from None


def _extract(bundle: Bundle, directory: str | Path) -> Path:
    target = Path(directory)
    if not target.is_dir():
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".unpack-", dir=target.parent))
        try:
            for name, data in bundle.files.items():
                path = staging / name
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
            os.replace(staging, target)
        except OSError:
            shutil.rmtree(staging, ignore_errors=True)
            if not target.is_dir():
                raise
    return target / bundle.program


def write_out(bundle: Bundle, directory: str | Path) -> list[Path]:
    """`softplc upload`: the files into `directory` at their bundle paths (overwritten)."""
    written = []
    for name, data in sorted(bundle.files.items()):
        path = Path(directory) / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        written.append(path)
    return written
