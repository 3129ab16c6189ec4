"""Input kinds by magic bytes, and safe extraction of a zip holding one glTF asset."""

from __future__ import annotations

import errno
import math
import os
import stat
import struct
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path, PurePosixPath
from typing import Literal

from ..errors import (
    InvalidAsset,
    LimitExceeded,
    PbrsrError,
    StorageError,
    UnprocessableAsset,
    UnsupportedAsset,
)
from ..limits import Limits
from .gltf_read import CHUNK_JSON, GLB_MAGIC, parse_json
from .uris import is_data_uri, relative_path, short_name

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
    """Unpack the one .gltf/.glb inside ``zip_path``, and the files it uses, into ``dest``
    (created); return the model's path.

    Only the model and the entries its ``buffers[].uri`` and ``images[].uri`` name
    (URI-decoded, relative to the model's folder) are written; every other entry is skipped
    unread, and a model that cannot be parsed uses nothing (loading it then says why).

    Refused before anything is written: entries with absolute paths, ``..``, backslashes or
    drive letters, symlinks and other special files, encrypted entries, no or several
    .gltf/.glb files (InvalidAsset); more than ``limits.max_zip_entries`` entries, an entry to
    unpack whose size is more than ``limits.max_compression_ratio`` times its compressed size,
    entries to unpack that together are more than ``limits.max_unpacked_bytes`` or more than
    that ratio times the zip's size (entries sharing compressed bytes) (LimitExceeded).
    While unpacking, the *actually decompressed* bytes are held to ``max_unpacked_bytes``
    too, whatever the headers claim. macOS ``__MACOSX/`` metadata is skipped. Nothing is
    written outside ``dest``.
    """
    zip_path, dest = Path(zip_path), Path(dest)
    try:
        zf = zipfile.ZipFile(zip_path)
    except _ZIP_READ_ERRORS as exc:
        raise InvalidAsset(f"the zip file cannot be read: {_short(exc)}") from None
    with zf:
        members = _members(zf, limits)
        model_info, model = _the_model(members)
        zip_size = zip_path.stat().st_size
        _check_sizes([(model_info, model)], zip_size, limits)
        wanted = {model} | _referenced(zf, model_info, model, limits)
        chosen = [(info, rel) for info, rel in members if rel in wanted and not info.is_dir()]
        _check_sizes(chosen, zip_size, limits)
        dest.mkdir(parents=True, exist_ok=True)
        root = dest.resolve()
        left = limits.max_unpacked_bytes
        for info, rel in chosen:
            left -= _unpack(zf, info, rel, root, left, limits)
        return root.joinpath(*model.parts)


def _members(zf: zipfile.ZipFile, limits: Limits) -> list[tuple[zipfile.ZipInfo, PurePosixPath]]:
    """Every entry but macOS metadata, with its checked archive-relative path."""
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
            raise InvalidAsset(f"the zip entry '{short_name(rel)}' is a symlink or special file")
        if info.flag_bits & 0x1:
            raise InvalidAsset(f"the zip entry '{short_name(rel)}' is encrypted")
        members.append((info, rel))
    return members


def _the_model(
    members: list[tuple[zipfile.ZipInfo, PurePosixPath]],
) -> tuple[zipfile.ZipInfo, PurePosixPath]:
    models = [
        (info, rel)
        for info, rel in members
        if not info.is_dir() and rel.suffix.lower() in (".gltf", ".glb")
    ]
    if not models:
        raise InvalidAsset("the zip holds no .gltf or .glb file")
    if len(models) > 1:
        names = ", ".join(str(rel) for _, rel in models[:5])
        raise InvalidAsset(f"the zip holds several .gltf/.glb files ({names}); send one")
    return models[0]


def _ratio(size: int, packed: int) -> float:
    return size / packed if packed else (math.inf if size else 0.0)


def _check_sizes(
    entries: list[tuple[zipfile.ZipInfo, PurePosixPath]], zip_size: int, limits: Limits
) -> None:
    """Refuse (LimitExceeded) ``entries`` whose sizes, as the zip declares them, are over the
    limits: one entry's compression ratio, their total, or their total against the zip's
    size (``zipfile`` never reads past a declared size, so these bound the real bytes)."""
    limit = limits.max_compression_ratio
    for info, rel in entries:
        ratio = _ratio(info.file_size, info.compress_size)
        if ratio > limit:
            raise LimitExceeded(
                f"the zip entry '{short_name(rel)}' unpacks {info.compress_size} bytes to "
                f"{info.file_size} ({ratio:.0f}:1); the limit is {limit:g}:1"
            )
    total = sum(info.file_size for info, _ in entries)
    if total > limits.max_unpacked_bytes:
        raise _over_unpacked(limits)
    ratio = _ratio(total, zip_size)
    if ratio > limit:
        raise LimitExceeded(
            f"the zip's files the asset uses unpack to {total} bytes from a zip of {zip_size} "
            f"bytes ({ratio:.0f}:1); the limit is {limit:g}:1"
        )


def _over_unpacked(limits: Limits) -> LimitExceeded:
    return LimitExceeded(
        f"the zip unpacks to more than {limits.max_unpacked_bytes} bytes (the limit)"
    )


def _referenced(
    zf: zipfile.ZipFile, info: zipfile.ZipInfo, model: PurePosixPath, limits: Limits
) -> set[PurePosixPath]:
    """The archive-relative paths the model's buffer and image URIs name."""
    if model.suffix.lower() == ".gltf":
        raw = _read(zf, info, model, limits.max_unpacked_bytes + 1)
        if len(raw) > limits.max_unpacked_bytes:
            raise _over_unpacked(limits)
    else:
        head = _read(zf, info, model, 20)
        if len(head) < 20:
            return set()
        magic, version, _, json_len, json_type = struct.unpack("<4sIIII", head)
        if magic != GLB_MAGIC or version != 2 or json_type != CHUNK_JSON:
            return set()
        if json_len > limits.max_unpacked_bytes:
            raise _over_unpacked(limits)
        raw = _read(zf, info, model, 20 + json_len)[20:]
    try:
        doc = parse_json(raw)
    except PbrsrError:
        return set()
    found: set[PurePosixPath] = set()
    for key, what in (("buffers", "buffer"), ("images", "image")):
        for i, item in enumerate(doc.get(key, [])):
            uri = item.get("uri")
            if not isinstance(uri, str) or is_data_uri(uri):
                continue
            try:
                found.add(model.parent / relative_path(uri, f"{what} {i}"))
            except InvalidAsset:
                continue  # loading the model refuses it
    return found


def _chunks(
    zf: zipfile.ZipFile, info: zipfile.ZipInfo, rel: PurePosixPath, most: int
) -> Iterator[bytes]:
    """Up to ``most`` decompressed bytes of one entry, in pieces; InvalidAsset when corrupt."""
    try:
        src = zf.open(info)
    except _ZIP_READ_ERRORS as exc:
        raise InvalidAsset(f"the zip entry '{short_name(rel)}' is corrupt: {_short(exc)}") from None
    with src:
        while most > 0:
            try:
                chunk = src.read(min(_CHUNK, most))
            except _ZIP_READ_ERRORS as exc:
                raise InvalidAsset(
                    f"the zip entry '{short_name(rel)}' is corrupt: {_short(exc)}"
                ) from None
            if not chunk:
                return
            most -= len(chunk)
            yield chunk


def _read(zf: zipfile.ZipFile, info: zipfile.ZipInfo, rel: PurePosixPath, most: int) -> bytes:
    return b"".join(_chunks(zf, info, rel, most))


def _unpack(
    zf: zipfile.ZipFile,
    info: zipfile.ZipInfo,
    rel: PurePosixPath,
    root: Path,
    left: int,
    limits: Limits,
) -> int:
    """Write one entry under ``root``; return its size (refused past ``left`` bytes)."""
    target = root.joinpath(*rel.parts)
    if root not in target.parents:
        raise InvalidAsset(f"the zip entry '{short_name(rel)}' points outside the archive")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise InvalidAsset(
            f"the zip entry '{short_name(rel)}' clashes with another entry (a file and a folder "
            "of the same name)"
        ) from None
    except OSError as exc:
        raise _unwritable(rel, exc) from None
    if target.parent.resolve() != target.parent or os.path.islink(target):
        raise InvalidAsset(f"the zip entry '{short_name(rel)}' goes through a link")
    try:
        out = open(target, "xb")  # noqa: SIM115 - closed below
    except (FileExistsError, IsADirectoryError):
        raise InvalidAsset(f"the zip has the entry '{short_name(rel)}' twice") from None
    except OSError as exc:
        raise _unwritable(rel, exc) from None
    written = 0
    with out:
        for chunk in _chunks(zf, info, rel, left + 1):
            written += len(chunk)
            if written > left:
                raise _over_unpacked(limits)
            try:
                out.write(chunk)
            except OSError as exc:
                raise _unwritable(rel, exc) from None
    return written


def _unwritable(rel: PurePosixPath, exc: OSError) -> PbrsrError:
    """The asset's fault (a name too long for the file system) or the storage's."""
    if exc.errno == errno.ENAMETOOLONG:
        return UnprocessableAsset(
            f"the zip entry '{short_name(rel)}' cannot be unpacked: its name is too long for "
            "the file system"
        )
    return StorageError(f"cannot unpack the zip: {exc.strerror or exc}")


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
