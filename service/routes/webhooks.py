"""``/v1/webhook-secret``: the caller's webhook signing secret (pbrsr_jobs.webhooks)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, Field

from pbrsr_jobs.webhooks import SIGNATURE_HEADER, TIMESTAMP_HEADER, key_secret, server_secret

from ..deps import OwnerDep, RedisDep, SettingsDep
from ..problems import PROBLEM_RESPONSES

router = APIRouter(tags=["webhooks"], responses=PROBLEM_RESPONSES)


class WebhookSecret(BaseModel):
    secret: str = Field(description="HMAC-SHA256 key of this API key's webhook signatures.")
    signature_header: str = SIGNATURE_HEADER
    timestamp_header: str = TIMESTAMP_HEADER
    scheme: str = Field(
        "v1=hex(HMAC-SHA256(secret, timestamp + '.' + body))",
        description="What the signature header holds.",
    )


@router.get("/v1/webhook-secret", response_model=WebhookSecret, summary="Webhook signing secret")
async def webhook_secret(redis: RedisDep, settings: SettingsDep, owner: OwnerDep) -> WebhookSecret:
    """The secret that signs the webhooks of this API key's jobs; the same on every call."""
    server = await run_in_threadpool(
        server_secret, redis, settings.key_prefix, settings.webhook_secret
    )
    return WebhookSecret(secret=key_secret(server, owner))
