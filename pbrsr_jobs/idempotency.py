"""Idempotency keys of ``POST /v1/jobs`` and ``POST /v1/batches``: the same request sent twice
makes one job (one batch).

A client may send ``Idempotency-Key: <1..255 printable ASCII characters>``. Keys are scoped
per owner (API key) and endpoint and live in Redis under
``<prefix>:<namespace>:<owner>:<sha256 of the key>`` (namespace ``idem`` for jobs,
``idem-batch`` for batches) as one string:

* ``pending <fingerprint> <token>`` - a request holds the key and is creating its job. Taken
  with ``SET NX`` and a short expiry (``pending_ttl_s``), so a process that dies mid-request
  frees the key by itself.
* ``done <fingerprint> <id>`` - the job (batch) was created; kept ``ttl_s`` (24 h by
  default).

The fingerprint is a hash of the uploaded files' bytes and the form's text fields (``options``):
the same key with another fingerprint is a reused key, not a retry. Completing or releasing a
reservation only touches the record while it is still that reservation's (compare and set
in a Lua script).
"""

from __future__ import annotations

import hashlib
import json
import uuid
from dataclasses import dataclass
from typing import Any

KEY_MAX_CHARS = 255
PENDING_TTL_S = 600  # longest a request may hold a key while its asset is checked

_COMPLETE = """
local v = redis.call('GET', KEYS[1])
if v == false or v == ARGV[1] then
  redis.call('SET', KEYS[1], ARGV[2], 'EX', ARGV[3])
  return 1
end
return 0
"""

_RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  return redis.call('DEL', KEYS[1])
end
return 0
"""


def valid_key(key: str) -> bool:
    """True for 1..255 printable ASCII characters (space to tilde)."""
    return 1 <= len(key) <= KEY_MAX_CHARS and all(" " <= ch <= "~" for ch in key)


def fingerprint(file_sha256: str | None, fields: dict[str, str]) -> str:
    """What makes two requests the same: the file's SHA-256 and the form's text fields
    (``options`` and any other; an empty field counts as absent)."""
    given = {name: value for name, value in fields.items() if value}
    text = json.dumps([file_sha256, given], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class Record:
    """What Redis holds for a key: ``pending`` (``ref`` = a reservation's token) or ``done``
    (``ref`` = the job or batch id)."""

    state: str
    fingerprint: str
    ref: str

    @property
    def done(self) -> bool:
        return self.state == "done"

    def encode(self) -> str:
        return f"{self.state} {self.fingerprint} {self.ref}"

    @classmethod
    def decode(cls, raw: bytes | str) -> Record:
        text = raw.decode() if isinstance(raw, bytes) else raw
        state, fp, ref = text.split(" ", 2)
        return cls(state, fp, ref)


@dataclass(frozen=True)
class Reservation:
    """This request holds the key: create the job, then :meth:`complete` or :meth:`release`."""

    keys: IdempotencyKeys
    redis_key: str
    record: Record

    def complete(self, ref: str) -> bool:
        """Remember ``ref`` (the job or batch id) for the key (``ttl_s``). False when another
        request took the key after this reservation expired (that one's record is kept)."""
        done = Record("done", self.record.fingerprint, ref)
        args = [self.record.encode(), done.encode(), self.keys.ttl_s]
        return bool(self.keys.complete_script(keys=[self.redis_key], args=args))

    def release(self) -> None:
        """Free the key (the request failed): a corrected retry may use it."""
        self.keys.release_script(keys=[self.redis_key], args=[self.record.encode()])


class IdempotencyKeys:
    """The idempotency records of one Redis (``redis``: a sync client), key prefix and
    endpoint (``namespace``)."""

    def __init__(
        self,
        redis: Any,
        prefix: str,
        ttl_s: int,
        *,
        pending_ttl_s: int = PENDING_TTL_S,
        namespace: str = "idem",
    ):
        self.redis = redis
        self.prefix = prefix
        self.namespace = namespace
        self.ttl_s = ttl_s
        self.pending_ttl_s = pending_ttl_s
        self.complete_script = redis.register_script(_COMPLETE)
        self.release_script = redis.register_script(_RELEASE)

    def redis_key(self, owner: str, key: str) -> str:
        digest = hashlib.sha256(key.encode()).hexdigest()
        return f"{self.prefix}:{self.namespace}:{owner}:{digest}"

    def get(self, owner: str, key: str) -> Record | None:
        raw = self.redis.get(self.redis_key(owner, key))
        return None if raw is None else Record.decode(raw)

    def reserve(self, owner: str, key: str, fp: str) -> Reservation | Record:
        """Take the key for a request with fingerprint ``fp`` (a :class:`Reservation`), or
        the record another request left (pending or done, with its fingerprint)."""
        rkey = self.redis_key(owner, key)
        while True:
            mine = Record("pending", fp, uuid.uuid4().hex)
            if self.redis.set(rkey, mine.encode(), nx=True, ex=self.pending_ttl_s):
                return Reservation(self, rkey, mine)
            raw = self.redis.get(rkey)
            if raw is not None:  # else it expired or was released in between: try again
                return Record.decode(raw)
