"""Input kinds by magic bytes, and safe extraction of a zip holding one glTF asset."""

from __future__ import annotations

import os
import stat
import struct
import zipfile
import zlib
from pathlib import Path, PurePosixPath
from typing import Literal

from ..errors import InvalidAsset, LimitExceeded, StorageError, UnsupportedAsset
from ..limits import Limits

AssetKind = Literal["glb", "gltf", "zip"]


def detect_kind(path: Path) -> AssetKind:
    """ "glb", "gltf" or "zip" from the file's first bytes (never its name).

    glTF JSON is recognised by a leading ``{`` (after an optional BOM and whitespace).
    Anything else raises UnsupportedAsset; an empty file raises InvalidAsset.
    """
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(1024)
    if not head:
        raise InvalidAsset(f"the file '{path.name}' is empty")
    if head[:4] == b"glTF":
        return "glb"
    if head[:4] in (b"PK\x03\x04", b"PK\x05\x06"):
        return "zip"
    if head.lstrip(b"\xef\xbb\xbf \t\r\n")[:1] == b"{":
        return "gltf"
    raise UnsupportedAsset(f"the file '{path.name}' is not a .glb, a .gltf or a .zip holding one")


_CHUNK = 1 << 20


def _safe_member(name: str) -> PurePosixPath:
    if "\x00" in name or "\\" in name:
        raise InvalidAsset(f"the zip entry '{name[:80]}' has an unsafe name")
    p = PurePosixPath(name)
    if p.is_absolute() or (p.parts and p.parts[0].endswith(":")) or ".." in p.parts:
        raise InvalidAsset(f"the zip entry '{name[:80]}' points outside the archive")
    parts = [x for x in p.parts if x not in ("", ".")]
    if not parts:
        raise InvalidAsset(f"the zip entry '{name[:80]}' has an empty name")
    return PurePosixPath(*parts)


def extract_zip(zip_path: Path, dest: Path, limits: Limits = Limits()) -> Path:
    """Extract ``zip_path`` into ``dest`` (created) and return the one .gltf/.glb inside.

    Refused: entries with absolute paths, ``..``, backslashes or drive letters (InvalidAsset);
    symlinks and other special files (InvalidAsset); more than ``limits.max_zip_entries``
    entries, or more than ``limits.max_unpacked_bytes`` of *actually decompressed* data
    (LimitExceeded: the bytes are counted while extracting, whatever the headers claim); no or
    several .gltf/.glb files (InvalidAsset). macOS ``__MACOSX/`` metadata is skipped. Nothing
    is written outside ``dest``.
    """
    zip_path, dest = Path(zip_path), Path(dest)
    try:
        zf = zipfile.ZipFile(zip_path)
    except _ZIP_READ_ERRORS as exc:
        raise InvalidAsset(f"the zip file cannot be read: {_short(exc)}") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > limits.max_zip_entries:
            raise LimitExceeded(
                f"the zip has {len(infos)} entries; the limit is {limits.max_zip_entries}"
            )
        members: list[tuple[zipfile.ZipInfo, PurePosixPath]] = []
        for info in infos:
            rel = _safe_member(info.filename)
            if rel.parts[0] == "__MACOSX":
                continue
            mode = (info.external_attr >> 16) & 0xFFFF
            file_type = stat.S_IFMT(mode)
            if info.create_system == 3 and file_type not in (0, stat.S_IFREG, stat.S_IFDIR):
                raise InvalidAsset(f"the zip entry '{rel}' is a symlink or special file")
            if info.flag_bits & 0x1:
                raise InvalidAsset(f"the zip entry '{rel}' is encrypted")
            members.append((info, rel))
        models = [
            rel
            for info, rel in members
            if not info.is_dir() and rel.suffix.lower() in (".gltf", ".glb")
        ]
        if not models:
            raise InvalidAsset("the zip holds no .gltf or .glb file")
        if len(models) > 1:
            names = ", ".join(str(m) for m in models[:5])
            raise InvalidAsset(f"the zip holds several .gltf/.glb files ({names}); send one")
        dest.mkdir(parents=True, exist_ok=True)
        root = dest.resolve()
        total = 0
        for info, rel in members:
            target = root.joinpath(*rel.parts)
            if root not in target.parents:
                raise InvalidAsset(f"the zip entry '{rel}' points outside the archive")
            try:
                if info.is_dir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
            except (FileExistsError, NotADirectoryError):
                raise InvalidAsset(
                    f"the zip entry '{rel}' clashes with another entry (a file and a folder "
                    "of the same name)"
                ) from None
            if target.parent.resolve() != target.parent or os.path.islink(target):
                raise InvalidAsset(f"the zip entry '{rel}' goes through a link")
            try:
                out = open(target, "xb")  # noqa: SIM115 - closed below
            except (FileExistsError, IsADirectoryError):
                raise InvalidAsset(f"the zip has the entry '{rel}' twice") from None
            except OSError as exc:
                raise StorageError(f"cannot unpack the zip: {exc.strerror or exc}") from None
            with out:
                try:
                    src = zf.open(info)
                except _ZIP_READ_ERRORS as exc:
                    raise InvalidAsset(f"the zip entry '{rel}' is corrupt: {_short(exc)}") from None
                with src:
                    while True:
                        try:
                            chunk = src.read(_CHUNK)
                        except _ZIP_READ_ERRORS as exc:
                            raise InvalidAsset(
                                f"the zip entry '{rel}' is corrupt: {_short(exc)}"
                            ) from None
                        if not chunk:
                            break
                        total += len(chunk)
                        if total > limits.max_unpacked_bytes:
                            raise LimitExceeded(
                                "the zip unpacks to more than "
                                f"{limits.max_unpacked_bytes} bytes (the limit)"
                            )
                        try:
                            out.write(chunk)
                        except OSError as exc:
                            raise StorageError(
                                f"cannot unpack the zip: {exc.strerror or exc}"
                            ) from None
        return root.joinpath(*models[0].parts)


# what zipfile raises on corrupt or hostile archives (reading side only: OSError here is a
# bad seek/read of the archive itself, e.g. an offset past its end)
_ZIP_READ_ERRORS = (
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    zlib.error,
    EOFError,
    OSError,
    ValueError,
    struct.error,
    NotImplementedError,  # an unsupported compression method
    RuntimeError,  # encrypted entries, and others zipfile reports this way
    UnicodeDecodeError,
    OverflowError,
)


def _short(exc: BaseException) -> str:
    """An exception's message without paths (zipfile messages may name the file)."""
    text = str(exc) or type(exc).__name__
    return text.replace(os.sep, "/").rsplit("/", 1)[-1][:120]
