"""Where the files the API and the workers share live: a local folder or an S3 bucket.

Job code (:class:`pbrsr_jobs.store.JobFiles`) talks to an :class:`ObjectStore` only; the
backend is chosen once by ``PBRSR_STORAGE_BACKEND`` (:func:`open_store`):

* :class:`FilesystemStore` - keys are files under ``PBRSR_STORAGE_DIR`` (shared by NFS on a
  farm). Objects are written to a hidden temporary name and renamed into place; a copy
  out or in is a hard link when both sides are on one filesystem. The API serves the files.
* :class:`S3Store` - keys are objects in ``PBRSR_S3_BUCKET`` under ``PBRSR_S3_KEY_PREFIX``,
  through the ``minio`` client (one small pure-Python package; boto3 brings botocore's
  service data). A PUT is atomic; downloads answer with a presigned URL.

Keys are ``/``-separated names pbrsr generates (``jobs/<id>/result.zip``), never a path from
a request. Every failure to reach the store (endpoint down, bucket missing, credentials
refused) raises :class:`StoreUnavailable` with a message naming the setting to check; a
missing object raises ``FileNotFoundError``.
"""

from __future__ import annotations

import contextlib
import io
import mimetypes
import os
import shutil
import uuid
from datetime import timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import urlsplit

if TYPE_CHECKING:
    from .settings import Settings


class StoreUnavailable(Exception):
    """The object store cannot be used now. The message says why and which setting to
    check; it never holds a secret."""


class ObjectStore(Protocol):
    """What job code needs of storage. Writes are atomic: a reader sees the old object or
    the whole new one."""

    def put_file(self, key: str, src: Path) -> None:
        """Store the file ``src`` under ``key`` (``src`` is left as it is)."""

    def put_bytes(self, key: str, data: bytes) -> None: ...

    def get_file(self, key: str, dest: Path) -> None:
        """Write object ``key`` to the file ``dest`` (its folder is created)."""

    def get_bytes(self, key: str) -> bytes: ...

    def exists(self, key: str) -> bool: ...

    def list(self, prefix: str) -> list[str]:
        """Keys under ``prefix`` (a folder: ends with ``/``), sorted."""

    def delete_prefix(self, prefix: str) -> None:
        """Delete every object under ``prefix`` (a folder: ends with ``/``); none is fine."""

    def delete(self, key: str) -> None:
        """Delete object ``key``; missing is fine."""

    def url(self, key: str, *, filename: str | None, media_type: str) -> str | None:
        """A presigned GET URL of ``key`` (served as ``media_type``, downloaded as
        ``filename``), or None when the API serves the object itself (:meth:`local_path`)."""

    def local_path(self, key: str) -> Path | None:
        """The object's file when the store is a local folder and it exists, else None."""

    def check(self) -> None:
        """Raise :class:`StoreUnavailable` unless objects can be written and deleted."""


def _check_key(key: str) -> str:
    parts = key.split("/")
    if not key or any(p in ("", ".", "..") or p.startswith(".") for p in parts):
        raise ValueError(f"malformed object key {key!r}")
    return key


def _check_prefix(prefix: str) -> str:
    if not prefix.endswith("/"):
        raise ValueError(f"a prefix is a folder ending with '/': {prefix!r}")
    _check_key(prefix[:-1])
    return prefix


def _media_type(key: str) -> str:
    return mimetypes.guess_type(key)[0] or "application/octet-stream"


class FilesystemStore:
    """Objects as files under ``root``. Hidden names (``.tmp-*``) are never objects."""

    def __init__(self, root: Path):
        self.root = Path(root).expanduser()

    def _path(self, key: str) -> Path:
        return self.root / _check_key(key)

    def _install(self, dest: Path, fill: Any) -> None:
        """Create ``dest`` atomically: ``fill(tmp)`` writes a hidden file, renamed into place."""
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(f".tmp-put-{uuid.uuid4().hex}")
        try:
            fill(tmp)
            os.replace(tmp, dest)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    def put_file(self, key: str, src: Path) -> None:
        self._install(self._path(key), lambda tmp: _link_or_copy(src, tmp))

    def put_bytes(self, key: str, data: bytes) -> None:
        self._install(self._path(key), lambda tmp: tmp.write_bytes(data))

    def get_file(self, key: str, dest: Path) -> None:
        src = self._path(key)
        if not src.is_file():
            raise FileNotFoundError(key)
        dest.parent.mkdir(parents=True, exist_ok=True)
        _link_or_copy(src, dest)

    def get_bytes(self, key: str) -> bytes:
        path = self._path(key)
        if not path.is_file():
            raise FileNotFoundError(key)
        return path.read_bytes()

    def exists(self, key: str) -> bool:
        return self._path(key).is_file()

    def list(self, prefix: str) -> list[str]:
        folder = self.root / _check_prefix(prefix)
        if not folder.is_dir():
            return []
        keys = []
        for path in folder.rglob("*"):
            rel = path.relative_to(self.root)
            hidden = any(p.startswith(".") for p in rel.parts)
            if not hidden and path.is_file() and not path.is_symlink():
                keys.append(rel.as_posix())
        return sorted(keys)

    def delete_prefix(self, prefix: str) -> None:
        folder = self.root / _check_prefix(prefix)
        if folder.is_dir() and not folder.is_symlink():
            shutil.rmtree(folder, ignore_errors=True)

    def delete(self, key: str) -> None:
        self._path(key).unlink(missing_ok=True)

    def url(self, key: str, *, filename: str | None, media_type: str) -> str | None:
        return None

    def local_path(self, key: str) -> Path | None:
        path = self._path(key)
        return path if path.is_file() else None

    def check(self) -> None:
        probe = self.root / "jobs" / f".write-probe-{uuid.uuid4().hex}"
        try:
            probe.parent.mkdir(parents=True, exist_ok=True)
            probe.write_bytes(b"ok")
            probe.unlink()
        except OSError as exc:
            raise StoreUnavailable(
                f"PBRSR_STORAGE_DIR is not a writable folder ({exc.strerror or exc})"
            ) from None


def _link_or_copy(src: Path, dest: Path) -> None:
    """A hard link (objects are replaced, never changed in place), else a copy."""
    try:
        os.link(src, dest)
    except OSError:
        shutil.copyfile(src, dest)


# S3 error codes that mean the credentials (or their rights) are wrong
_CREDENTIAL_CODES = {
    "AccessDenied",
    "InvalidAccessKeyId",
    "SignatureDoesNotMatch",
    "InvalidToken",
    "ExpiredToken",
    "InvalidClientTokenId",
}


class S3Store:
    """Objects in an S3-compatible bucket (AWS S3, MinIO, Ceph RGW, ...)."""

    def __init__(
        self,
        endpoint_url: str,
        bucket: str,
        *,
        region: str,
        access_key: str | None,
        secret_key: str | None,
        key_prefix: str = "",
        presign_expiry_s: int = 900,
        path_style: bool = True,
        public_url: str | None = None,
        connect_timeout_s: float = 5.0,
        read_timeout_s: float = 120.0,
        retries: int = 2,
    ):
        import certifi
        import urllib3
        from minio import Minio

        self.endpoint_url = endpoint_url
        self.bucket = bucket
        self.key_prefix = key_prefix.strip("/") + "/" if key_prefix.strip("/") else ""
        self.expiry = timedelta(seconds=presign_expiry_s)
        http = urllib3.PoolManager(
            timeout=urllib3.Timeout(connect=connect_timeout_s, read=read_timeout_s),
            maxsize=16,
            cert_reqs="CERT_REQUIRED",
            ca_certs=certifi.where(),
            retries=urllib3.Retry(
                total=retries, backoff_factor=0.2, status_forcelist=[500, 502, 503, 504]
            ),
        )

        def client(url: str) -> Minio:
            where = urlsplit(url)
            made = Minio(
                where.netloc,
                access_key=access_key,
                secret_key=secret_key,
                secure=where.scheme == "https",
                region=region,  # known: presigning needs no request, no location lookup
                http_client=http,
            )
            if path_style:
                made.disable_virtual_style_endpoint()
            else:
                made.enable_virtual_style_endpoint()
            return made

        self.client = client(endpoint_url)
        # presigned URLs are signed for the host clients use (signing sends no request)
        self.signer = client(public_url) if public_url else self.client

    def _name(self, key: str) -> str:
        return self.key_prefix + _check_key(key)

    def _call(self, what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        """``fn(*args)`` with the client's errors turned into FileNotFoundError (no such
        key) or :class:`StoreUnavailable` (anything that makes the store unusable)."""
        from minio.error import MinioException, S3Error
        from urllib3.exceptions import HTTPError

        try:
            return fn(*args, **kwargs)
        except S3Error as exc:
            if exc.code in ("NoSuchKey", "ResourceNotFound"):
                raise FileNotFoundError(what) from None
            raise self._unavailable(exc.code) from None
        except (MinioException, HTTPError) as exc:  # a local file's OSError passes through
            raise StoreUnavailable(
                f"cannot reach the S3 endpoint PBRSR_S3_ENDPOINT_URL={self.endpoint_url} "
                f"({type(exc).__name__})"
            ) from None

    def _unavailable(self, code: str | None) -> StoreUnavailable:
        if code == "NoSuchBucket":
            return StoreUnavailable(
                f"the bucket PBRSR_S3_BUCKET={self.bucket!r} does not exist at "
                f"{self.endpoint_url}; create it or fix the name"
            )
        if code in _CREDENTIAL_CODES:
            return StoreUnavailable(
                f"the S3 endpoint {self.endpoint_url} refused the credentials ({code}); check "
                "PBRSR_S3_ACCESS_KEY, PBRSR_S3_SECRET_KEY and their rights on "
                f"bucket {self.bucket!r}"
            )
        return StoreUnavailable(f"the S3 endpoint {self.endpoint_url} answered {code}")

    def put_file(self, key: str, src: Path) -> None:
        name = self._name(key)
        self._call(key, self.client.fput_object, self.bucket, name, str(src), _media_type(key))

    def put_bytes(self, key: str, data: bytes) -> None:
        name = self._name(key)
        self._call(
            key,
            self.client.put_object,
            self.bucket,
            name,
            io.BytesIO(data),
            len(data),
            _media_type(key),
        )

    def get_file(self, key: str, dest: Path) -> None:
        dest.parent.mkdir(parents=True, exist_ok=True)
        self._call(key, self.client.fget_object, self.bucket, self._name(key), str(dest))

    def get_bytes(self, key: str) -> bytes:
        def read() -> bytes:
            resp = self.client.get_object(self.bucket, self._name(key))
            try:
                return resp.read()
            finally:
                resp.close()
                resp.release_conn()

        return self._call(key, read)

    def exists(self, key: str) -> bool:
        try:
            self._call(key, self.client.stat_object, self.bucket, self._name(key))
        except FileNotFoundError:
            return False
        return True

    def list(self, prefix: str) -> list[str]:
        full = self.key_prefix + _check_prefix(prefix)

        def names() -> list[str]:
            found = self.client.list_objects(self.bucket, prefix=full, recursive=True)
            return [o.object_name for o in found if o.object_name and not o.is_dir]

        cut = len(self.key_prefix)
        return sorted(n[cut:] for n in self._call(prefix, names))

    def delete_prefix(self, prefix: str) -> None:
        from minio.deleteobjects import DeleteObject

        keys = self.list(prefix)
        if not keys:
            return

        def delete() -> list[Any]:
            objects = [DeleteObject(self._name(k)) for k in keys]
            return list(self.client.remove_objects(self.bucket, objects))

        errors = self._call(prefix, delete)
        if errors:
            raise self._unavailable(errors[0].code)

    def delete(self, key: str) -> None:
        self._call(key, self.client.remove_object, self.bucket, self._name(key))

    def url(self, key: str, *, filename: str | None, media_type: str) -> str | None:
        headers = {"response-content-type": media_type}
        if filename:
            headers["response-content-disposition"] = f'attachment; filename="{filename}"'
        return self._call(
            key,
            self.signer.presigned_get_object,
            self.bucket,
            self._name(key),
            expires=self.expiry,
            response_headers=headers,
        )

    def local_path(self, key: str) -> Path | None:
        return None

    def check(self) -> None:
        if not self._call("bucket", self.client.bucket_exists, self.bucket):
            raise self._unavailable("NoSuchBucket")
        probe = f"{self.key_prefix}.write-probe-{uuid.uuid4().hex}"
        self._call(probe, self.client.put_object, self.bucket, probe, io.BytesIO(b""), 0)
        with contextlib.suppress(FileNotFoundError):
            self._call(probe, self.client.remove_object, self.bucket, probe)


def open_store(settings: Settings) -> ObjectStore:
    """The store ``settings`` name (``PBRSR_STORAGE_BACKEND``); nothing is contacted yet
    (:meth:`ObjectStore.check` does that)."""
    if settings.storage_backend == "filesystem":
        return FilesystemStore(settings.storage_dir)
    assert settings.s3_endpoint_url and settings.s3_bucket  # the settings validated it
    return S3Store(
        settings.s3_endpoint_url,
        settings.s3_bucket,
        region=settings.s3_region,
        access_key=_secret(settings.s3_access_key),
        secret_key=_secret(settings.s3_secret_key),
        key_prefix=settings.s3_key_prefix,
        presign_expiry_s=settings.s3_presign_expiry_s,
        path_style=settings.s3_path_style,
        public_url=settings.s3_public_url,
    )


def _secret(value: Any) -> str | None:
    return None if value is None else value.get_secret_value()
