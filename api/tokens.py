"""Short-lived signed read tokens for one job's GET routes (events, images, downloads).

EventSource, ``<img>`` and download links cannot send an ``Authorization`` header; instead of the
API key in the URL (where it would show in logs and history), the dashboard sends ``?token=`` with
a token that reads one job for a short time:

    token = "<job id>.<expiry, unix seconds>.<base64url HMAC-SHA256(secret, job id | expiry)[:16]>"

The secret is ``NDRF_TOKEN_SECRET`` (default: derived from the API keys, so every API process
agrees without configuration).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import time


def _mac(secret: bytes, job_id: str, expires: int) -> str:
    digest = hmac.new(secret, f"{job_id}|{expires}|read".encode(), hashlib.sha256).digest()[:16]
    return base64.urlsafe_b64encode(digest).decode().rstrip("=")


def sign(secret: bytes, job_id: str, seconds: int, now: float | None = None) -> str:
    expires = int((time.time() if now is None else now) + seconds)
    return f"{job_id}.{expires}.{_mac(secret, job_id, expires)}"


def verify(secret: bytes, token: str, job_id: str, now: float | None = None) -> bool:
    """Whether ``token`` reads ``job_id`` now."""
    try:
        token_job, expires_text, mac = token.split(".")
        expires = int(expires_text)
    except ValueError:
        return False
    if token_job != job_id or expires < (time.time() if now is None else now):
        return False
    return hmac.compare_digest(mac, _mac(secret, job_id, expires))
