"""Warm view children: one sandboxed child per (job, checkpoint) kept for a short idle time, so
that an orbit viewer's next view pays neither the child's start (Python, Mitsuba, torch), nor the
scene's load, nor the checkpoint's restore, nor compiling Dr.Jit's kernels again.

The child is the same sandbox as a one-off view (``services.jobs.child`` mode ``views``: no
network, a read-only filesystem but its work folder, memory and CPU limits); the API process
still never loads a scene. It restores the checkpoint once, then answers one ``view`` frame at a
time until its stdin closes. A session is keyed by the job and the SHA-256 of the checkpoint's
bytes: a running job's newer checkpoint starts a new session (the older one of that job is
closed). Sessions idle for ``keep_seconds`` are closed by a reaper thread; at most ``most``
sessions live at once (the least recently used one is closed first); a session older than
``limits.view_seconds`` x 4 is closed at its next use (its CPU limit grows with each view). A
child that fails or times out is killed and its session dropped; the request fails as a one-off
view would.

Concurrent views of one checkpoint are serialized, never refused: one request starts the
session while the others wait for it (one child, not one per request), then each view holds the
session's lock in turn. A session evicted, replaced or dropped while a view holds it is only
*retired*: the view in flight finishes and the session is closed when it lets go; a view that
was waiting for it then finds it closed and is answered by a fresh session (``views.py``).

Each view's files are written by the child into a folder of its work folder, which the session
moves out of the child's reach (into the folder the caller names) before it lets go of the lock:
neither the next view nor a close touches them (:mod:`services.jobs.view_files`).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import queue
import secrets
import shutil
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

from schemas.job import JobSpec
from schemas.views import ViewRequest
from services.jobs.frames import FrameError, read_frame, start_frame, write_frame
from services.jobs.isolation import Child, ChildFailed, ChildLimits
from services.jobs.preflight import checks_folder, upload_limits
from services.settings import Limits
from services.uploads.staging import stage_job

log = logging.getLogger(__name__)


class ViewSession:
    """One warm child for one job's checkpoint; :meth:`view` one request at a time."""

    def __init__(self, job_id: str, digest: str, spec: JobSpec, checkpoint: bytes, limits: Limits,
                 owner: str = ""):
        self.job_id, self.digest, self.owner = job_id, digest, owner
        self.kept = True   # False: not among the warm children (no room that its key may take): closed after use
        self.retired = self.closed = False   # retired: closed once the view holding it lets go
        self.wall = limits.view_seconds
        self.started = self.used = time.monotonic()
        self.lock = threading.Lock()
        self.folder = Path(tempfile.mkdtemp(prefix="ndrf-views-", dir=checks_folder()))
        self.frames: queue.Queue = queue.Queue()
        try:
            scene_file = stage_job(spec, self.folder / "scene", upload_limits(limits))
            (self.folder / "latest.pt").write_bytes(checkpoint)
            lifetime = ChildLimits(memory_bytes=limits.child_memory_bytes, cpu_seconds=int(limits.view_seconds) * 8,
                                   wall_seconds=limits.view_seconds)
            self.child = Child("views", lifetime, self.folder, label=f"views-{job_id}")
        except BaseException:
            shutil.rmtree(self.folder, ignore_errors=True)
            raise
        start = {"spec": spec.model_dump(mode="json"), "scene_file": str(scene_file) if scene_file else None,
                 "checkpoint_file": str(self.folder / "latest.pt")}
        threading.Thread(target=self._read, name=f"views-{job_id}", daemon=True).start()
        with contextlib.suppress(BrokenPipeError):   # it died at once: the first view says why
            write_frame(self.child.stdin, "start", *start_frame(start))

    def _read(self) -> None:
        while True:
            try:
                frame = read_frame(self.child.stdout)
            except (FrameError, OSError) as exc:
                frame = None
                log.info("view child of job %s: %s", self.job_id, exc)
            if frame is None:
                self.frames.put(None)
                return
            if frame[0] != "ready":
                self.frames.put(frame)

    def alive(self) -> bool:
        return self.child.proc.poll() is None

    def view(self, request: ViewRequest, out: Path) -> tuple[str, dict, dict[str, bytes]]:
        """The child's answer to ``request``: ``(kind, meta, blobs)``, the view's files moved into
        ``out`` (out of the child's reach, before another view or a close can touch them);
        :class:`ChildFailed` (the session is then dead) when it died, took longer than
        ``view_seconds``, or was closed while this request waited for it."""
        try:
            with self.lock:
                return self._view(request, out)
        finally:
            if self.retired and not self.closed:   # retired while it answered: closed now that it has
                self.retire()

    def _view(self, request: ViewRequest, out: Path) -> tuple[str, dict, dict[str, bytes]]:
        if self.closed or self.retired:   # closed while this request waited for it: a fresh one answers
            self.retired = True            # (views.render_warm retries on a retired session)
            self.close()
            raise ChildFailed("the view child was closed before this view")
        self.used = time.monotonic()
        written = self.folder / f"out-{secrets.token_hex(6)}"
        try:
            write_frame(self.child.stdin, "view", {"request": request.model_dump(mode="json"), "out": str(written)})
            frame = self.frames.get(timeout=self.wall)
        except (BrokenPipeError, OSError, ValueError):   # ValueError: its stdin was closed meanwhile
            frame = None
        except queue.Empty:
            self.close()
            raise ChildFailed(self.child.describe_exit("the view", timed_out=True)) from None
        finally:
            self.used = time.monotonic()
        if frame is None:
            self.close()
            raise ChildFailed(self.child.describe_exit("the view"))
        if frame[0] == "viewed":
            with contextlib.suppress(OSError):   # none: the caller says the child wrote no files
                os.rename(written, out)
        else:
            shutil.rmtree(written, ignore_errors=True)
        return frame

    def retire(self) -> None:
        """Close the session once no view holds it: now when it is idle, else when the view in
        flight ends (:meth:`view`)."""
        self.retired = True
        if self.lock.acquire(blocking=False):
            try:
                self.close()
            finally:
                self.lock.release()

    def close(self) -> None:
        self.closed = True
        with contextlib.suppress(OSError):
            self.child.stdin.close()
        self.child.kill()
        shutil.rmtree(self.folder, ignore_errors=True)


class ViewSessions:
    """The warm view children of one API process."""

    def __init__(self, keep_seconds: float = 60.0, most: int = 2):
        self.keep_seconds, self.most = keep_seconds, most
        self.sessions: dict[tuple[str, str], ViewSession] = {}
        self.lock = threading.Lock()
        self._starting: dict[tuple[str, str], list] = {}   # [lock, users]: one start per checkpoint at a time
        self.stopping = threading.Event()
        self._reaper: threading.Thread | None = None

    @property
    def enabled(self) -> bool:
        return self.keep_seconds > 0 and self.most > 0

    def _evictable(self, owner: str) -> tuple[str, str] | None:
        """The session to close to make room for one of ``owner``: its own least recently used
        one, else the least recently used one of a key holding more than one; None: every
        session belongs to another key holding just that one (none of them is evicted)."""
        own = [k for k, s in self.sessions.items() if s.owner == owner]
        if not own:
            held = Counter(s.owner for s in self.sessions.values())
            own = [k for k, s in self.sessions.items() if held[s.owner] > 1]
        return min(own, key=lambda k: self.sessions[k].used) if own else None

    def session(self, job_id: str, spec: JobSpec, checkpoint: bytes, limits: Limits,
                owner: str = "") -> tuple[ViewSession, bool]:
        """The warm session of this job's checkpoint, started if needed; ``(session, started)``.
        Warm children belong to the key that owns the job: a key makes room by closing its own,
        or those of a key holding several, never another key's only one (the session is then
        not kept: ``kept`` False, closed after its view)."""
        digest = hashlib.sha256(checkpoint).hexdigest()
        key = (job_id, digest)
        with self.lock:
            starting = self._starting.setdefault(key, [threading.Lock(), 0])
            starting[1] += 1
        try:
            with starting[0]:   # concurrent first views of a checkpoint wait for one child, not one each
                return self._session(key, spec, checkpoint, limits, owner)
        finally:
            with self.lock:
                starting[1] -= 1
                if not starting[1]:
                    self._starting.pop(key, None)

    def _session(self, key: tuple[str, str], spec: JobSpec, checkpoint: bytes, limits: Limits,
                 owner: str) -> tuple[ViewSession, bool]:
        job_id, digest = key
        closing: list[ViewSession] = []
        with self.lock:
            current = self.sessions.get(key)
            if current is not None and current.alive() and time.monotonic() - current.started < 4 * current.wall:
                return current, False
            if current is not None:
                closing.append(self.sessions.pop(key))
            closing += [self.sessions.pop(k) for k in list(self.sessions) if k[0] == job_id]   # older checkpoints
            keep = True
            while len(self.sessions) >= self.most:
                victim = self._evictable(owner)
                if victim is None:
                    keep = False
                    break
                closing.append(self.sessions.pop(victim))
        for old in closing:   # a view in flight on one finishes first
            old.retire()
        fresh = ViewSession(job_id, digest, spec, checkpoint, limits, owner)
        fresh.kept = keep
        with self.lock:
            other = self.sessions.get(key)
            if keep and (other is None or not other.alive()):
                self.sessions[key] = fresh
            if self._reaper is None:
                self._reaper = threading.Thread(target=self._reap, name="view-sessions-reaper", daemon=True)
                self._reaper.start()
        if other is not None and other.alive():   # another request started one meanwhile: use that one
            fresh.close()
            return other, True
        return fresh, True

    def drop(self, session: ViewSession) -> None:
        with self.lock:
            if self.sessions.get((session.job_id, session.digest)) is session:
                del self.sessions[(session.job_id, session.digest)]
        session.retire()

    def _reap(self) -> None:
        while not self.stopping.wait(min(5.0, self.keep_seconds / 2)):
            now = time.monotonic()
            closing = []
            with self.lock:
                for key, session in list(self.sessions.items()):
                    if now - session.used > self.keep_seconds and session.lock.acquire(blocking=False):
                        closing.append(self.sessions.pop(key))
            for session in closing:   # a view that waited on it meanwhile gets a fresh session (views.py)
                log.info("view child of job %s idle for %.0f s: closed", session.job_id, self.keep_seconds)
                session.close()
                session.lock.release()

    def close(self) -> None:
        self.stopping.set()
        with self.lock:
            closing = list(self.sessions.values())
            self.sessions.clear()
        for session in closing:
            session.close()
