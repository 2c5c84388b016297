"""The cell-controller service: the job API over Zenoh (docs/API.md) in front of one arm.

Jobs run one at a time, in submission order (there is one arm), in the cell's job worker process
(cellctl.service.worker), which one queue thread feeds and waits for; the Zenoh callbacks only
validate, queue and read the store, so the cell answers status and job queries while a scan runs,
and a job that crashes ends as failed while the cell serves on. Every job's life is in the SQLite
store before anyone is told about it: a client that sees an event can always read the matching
record."""

from __future__ import annotations

import fcntl
import json
import logging
import os
import secrets
import signal
import sys
import threading
import time
from collections import deque
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

import zenoh

from cellctl.config import CellConfig, ServiceConfig
from cellctl.scan.modes import MODES
from cellctl.service import logs
from cellctl.service.api import (MAX_MESSAGE_BYTES, MAX_PAYLOAD_BYTES, TERMINAL_STATES, ApiError, Artifacts,
                                 CancelReply, CancelRequest, CellStatus, CommissionPaintReply, CommissionPaintRequest,
                                 FileChunkRequest, JobList, Keys, ListJobsRequest, PaintModel, PaintReply,
                                 ResultSummary, ScanDrawingRequest, SubmitReply, dumps, parse_payload)
from cellctl.service.client import CellUnreachable, open_config, zenoh_error
from cellctl.service.events import JobEvents
from cellctl.service.files import JobFiles
from cellctl.service.readiness import READINESS_PERIOD_S, DeviceWatch
from cellctl.service.retention import prune
from cellctl.service.store import JobStore, StoreError, now_iso
from cellctl.scan.spec import JobSpec
from cellctl.service.worker import Worker, summary_from_file
from sim.scenes.catalog import SCENE_NAMES

log = logging.getLogger("cellctl.service.server")
JSON = zenoh.Encoding.APPLICATION_JSON


def version() -> str:
    try:
        return metadata.version("scrapcell")
    except metadata.PackageNotFoundError:
        return "unknown"


def new_job_id() -> str:
    return datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ") + "-" + secrets.token_hex(3)


def zenoh_config(scfg: ServiceConfig, cfg_dir: Path, *, listen: list[str] | None = None,
                 connect: list[str] | None = None) -> zenoh.Config:
    """Peer listening on loopback by default, or client of a router. Explicit endpoints turn multicast
    scouting off: a cell must not wander into another cell's session on the shop network."""
    listen = scfg.listen if listen is None else listen
    connect = scfg.connect if connect is None else connect
    zenoh_file, ca = scfg.zenoh_config_path(cfg_dir), scfg.tls_ca_path(cfg_dir)
    conf = zenoh.Config.from_file(str(zenoh_file)) if zenoh_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(scfg.zenoh_mode))
    if ca:
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ca)))
    if scfg.zenoh_mode == "peer" and listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen or connect:
        conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))  # a huge query is dropped
    return conf


class ServiceError(RuntimeError):
    """The service cannot start (its data dir is in use by another one)."""


STOPPED_AS = {"operator": "cancelled", "timeout": "timeout", "shutdown": "interrupted"}  # reason -> terminated_by


class JobControl:
    """The running job's cancel switch; the first reason wins (operator, timeout, shutdown)."""

    def __init__(self, job_id: str):
        self.job_id = job_id
        self.cancel = threading.Event()
        self.reason: str | None = None
        self._lock = threading.Lock()

    def request(self, reason: str) -> bool:
        with self._lock:
            if self.cancel.is_set():
                return False
            self.reason = reason
            self.cancel.set()
            return True


class CellService:
    def __init__(self, cfg: CellConfig, cfg_path: Path, data_dir: str | Path | None = None, *,
                 listen: list[str] | None = None, connect: list[str] | None = None):
        from cellctl.config import cell_planners_config

        self.cfg, self.cfg_path, self.scfg = cfg, Path(cfg_path), cfg.service
        if self.scfg.rerun_connect:
            self.cfg = cfg.model_copy(update={"rerun_connect": self.scfg.rerun_connect})
        self.data_dir = Path(data_dir or self.scfg.data_dir).resolve()
        self.keys = Keys(cfg.cell_id)
        self.default_max_steps = cell_planners_config(cfg, self.cfg_path).max_steps
        # resolved once: a request's scene path must resolve inside one of these (symlinks followed)
        self.scene_dirs = [(self.cfg_path.parent / d).resolve() for d in self.scfg.scene_dirs]
        self.listen = self.scfg.listen if listen is None else listen
        self.connect = self.scfg.connect if connect is None else connect
        self.store = JobStore(self.data_dir / "jobs.sqlite")
        self._queue: deque[str] = deque()
        self._cv = threading.Condition()
        self._running: JobControl | None = None
        self._accepting = False
        self._stopping = threading.Event()
        self.events = JobEvents(self.store, self.keys, lambda: self.session)
        self.files = JobFiles()
        self._worker: threading.Thread | None = None
        self._job_worker = Worker()  # the jobs' own process (cellctl.service.worker)
        self.session: zenoh.Session | None = None
        self._declared: list = []
        self._lock_file = None
        self.started_at = now_iso()
        self._t0 = time.monotonic()
        self.devices = DeviceWatch(self.cfg, MODES[cfg.mode])  # readiness, and fcisim's own franky-sim

    def job_dir(self, job_id: str) -> Path:
        return self.data_dir / "jobs" / job_id

    # --- life cycle -------------------------------------------------------------------------------
    def start(self) -> None:
        """Take over what a previous process left unfinished (the job it ran is interrupted, the queued
        ones queue again), open the session, declare the API, start the worker. On any failure the
        session is closed again."""
        if self.scfg.job_profile != "scan" and not self.devices.mode.twin_arm:  # a load-test job on a real arm: never
            raise ServiceError(f"service.job_profile {self.scfg.job_profile} is for load tests in the twin; "
                               f"mode {self.cfg.mode} needs job_profile scan")
        self._lock_data_dir()
        recovered, requeued = self.store.recover("the service stopped before the job ended",
                                                 requeue=self.scfg.requeue_after_restart)
        try:
            self.devices.start()
        except BaseException:
            self.close()
            raise
        conf = zenoh_config(self.scfg, self.cfg_path.parent, listen=self.listen, connect=self.connect)
        if self.scfg.zenoh_mode == "client":  # a refused session says why: certificates, password, or no router
            creds = f"the user and password in {self.scfg.zenoh_config_file}" if self.scfg.zenoh_config_file else \
                "service.zenoh_config_file (the cell's router credentials, deploy/zenoh/cell.json5)"
            self.session = open_config(conf, list(self.connect), creds)
        else:
            self.session = zenoh.open(conf)
        try:
            s, k = self.session, self.keys
            self._declared.append(s.declare_queryable(k.status, self._on_status_query))
            self._declared.append(s.declare_queryable(k.jobs_tree, self._on_jobs_query))
            self._declared.append(s.declare_queryable(k.paint, self._on_paint_query))
            self._declared.append(s.declare_queryable(k.paint_commission, self._on_commission_query))
            for job_id in recovered:
                self.events.emit(job_id, "interrupted", "interrupted", message="the service stopped before the job "
                                 "ended")
            for job_id in requeued:  # in their order, before any new submit
                self._queue.append(job_id)
                self.events.emit(job_id, "queued", "queued", message=f"the service restarted; queued again at "
                                 f"position {len(self._queue)}")
            self._worker = threading.Thread(target=self._work, name="cell-worker", daemon=True)
            self._worker.start()
            self.devices.watch()
            with self._cv:
                self._accepting = True
            self._declared.append(s.liveliness().declare_token(k.alive))  # last: alive means ready
        except BaseException:
            self.close()
            raise
        if recovered:
            log.warning("marked %d unfinished job(s) interrupted: %s", len(recovered), ", ".join(recovered))
        if requeued:
            log.warning("queued again after a restart: %s", ", ".join(requeued))

    def _lock_data_dir(self) -> None:
        """One service per data dir: a second one would mark the first one's running job interrupted."""
        f = open(self.data_dir / "service.lock", "a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            pid = f.read().strip() or "?"
            f.close()
            raise ServiceError(f"{self.data_dir} is in use by another service (pid {pid})") from None
        f.truncate(0)
        f.write(str(os.getpid()))
        f.flush()
        self._lock_file = f

    def stop(self, grace_s: float | None = None) -> None:
        """Take no more jobs, cancel the running one and wait for it to write its partial result (at
        most ``grace_s``). The queued ones stay queued for the next start (``service.requeue_after_restart``),
        else they are interrupted."""
        grace_s = self.scfg.shutdown_grace_s if grace_s is None else grace_s
        with self._cv:
            self._accepting = False
            self._stopping.set()
            self.devices.stop()
            queued = list(self._queue)
            self._queue.clear()
            running = self._running
            if running is not None:
                running.request("shutdown")
            self._cv.notify_all()
        if queued and self.scfg.requeue_after_restart:
            log.info("%d queued job(s) stay queued for the next start: %s", len(queued), ", ".join(queued))
        elif queued:
            for job_id in queued:
                self._finish(job_id, "interrupted", "the service was stopped before the job started",
                             error="interrupted: the service was stopped before the job started")
        if self._worker is not None:
            self._worker.join(grace_s)
            if self._worker.is_alive() and running is not None:
                log.error("job %s did not stop within %.0f s; marking it interrupted", running.job_id, grace_s)
                note = f"the service was stopped; the job did not stop within {grace_s:.0f} s"
                self._finish(running.job_id, "interrupted", note, error=f"interrupted: {note}")

    def close(self) -> None:
        """Undeclare everything and close the Zenoh session (an unclosed session can hang the
        interpreter's exit for minutes). Idempotent."""
        while self._declared:
            obj = self._declared.pop()
            try:
                obj.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        if self.session is not None:
            try:
                self.session.close()
            finally:
                self.session = None
        self._stopping.set()
        self._job_worker.close()  # a job that did not stop within the grace holds the arm: killed
        self.devices.close()
        self.store.close()
        if self._lock_file is not None:
            self._lock_file.close()  # releases the flock
            self._lock_file = None

    # --- Zenoh handlers ---------------------------------------------------------------------------
    def _on_status_query(self, query: zenoh.Query) -> None:
        with query:  # replied on the cell's own key: `cell/*/status` gets one reply per cell, each named
            self._answer(query, lambda payload: self.status(), reply_key=self.keys.status)

    def _on_jobs_query(self, query: zenoh.Query) -> None:
        """One queryable on cell/<id>/jobs/** (separate ones for jobs/submit and jobs/* would both
        receive a query on jobs/submit)."""
        with query:
            self._answer(query, lambda payload: self._route(str(query.key_expr), payload))

    def _on_paint_query(self, query: zenoh.Query) -> None:
        with query:
            self._answer(query, lambda payload: self.paint())

    def _on_commission_query(self, query: zenoh.Query) -> None:
        with query:
            self._answer(query, lambda payload: self._commission(str(query.key_expr), payload))

    def _commission(self, key: str, payload: bytes | None) -> CommissionPaintReply:
        if key != self.keys.paint_commission:  # a command answers its own key only, never a wildcard's query
            raise ApiError("invalid_request", f"{key}: wildcards are not served; query {self.keys.paint_commission}")
        return self.commission_paint(parse_payload(payload, CommissionPaintRequest))

    def _answer(self, query: zenoh.Query, handle, reply_key: str | None = None) -> None:
        key = str(query.key_expr)
        try:
            raw = query.payload
            if raw is not None and len(raw) > MAX_PAYLOAD_BYTES:  # every key, before copying it
                raise ApiError("payload_too_large", f"payload is {len(raw)} bytes; at most {MAX_PAYLOAD_BYTES} are "
                               f"accepted")
            reply = handle(raw.to_bytes() if raw is not None else None)
            query.reply(reply_key or key, dumps(reply), encoding=JSON)
        except ApiError as e:
            log.info("%s: %s", key, e)
            query.reply_err(dumps(e.reply()), encoding=JSON)
        except Exception:  # noqa: BLE001 - a bug answers internal_error; the service keeps serving
            log.exception("query on %s failed", key)
            query.reply_err(dumps(ApiError("internal_error", "the service failed on this request; see its log")
                                  .reply()), encoding=JSON)

    def _route(self, key: str, payload: bytes | None):
        if any(ch in key for ch in "*$"):
            raise ApiError("invalid_request", f"{key}: wildcards are not served; query {self.keys.jobs}, "
                           f"{self.keys.submit}, {self.keys.jobs}/<job_id>, .../cancel, .../files or "
                           f".../files/<name>")
        rest = key[len(self.keys.jobs):].strip("/")
        parts = rest.split("/") if rest else []
        if not parts:
            return self.list_jobs(parse_payload(payload, ListJobsRequest, required=False))
        if parts == ["submit"]:
            return self.submit(parse_payload(payload, ScanDrawingRequest))
        if len(parts) == 1:
            return self.job(parts[0])
        if len(parts) == 2 and parts[1] == "cancel":
            return self.cancel(parts[0], parse_payload(payload, CancelRequest, required=False))
        if len(parts) == 2 and parts[1] == "events":
            raise ApiError("invalid_request", f"{key} is published, not queried: subscribe to it")
        if len(parts) == 2 and parts[1] == "files":
            return self.files.listing(parts[0], self._ended_folder(parts[0]))
        if len(parts) == 3 and parts[1] == "files":
            req = parse_payload(payload, FileChunkRequest, required=False)
            return self.files.chunk(parts[0], self._ended_folder(parts[0]), parts[2], req)
        raise ApiError("invalid_request", f"no such key: {key}")

    # --- the API ----------------------------------------------------------------------------------
    def status(self) -> CellStatus:
        with self._cv:
            queue_length, running, accepting = len(self._queue), self._running, self._accepting
        rd = self.devices.readiness()
        devices = self.devices.describe()
        if self.scfg.job_profile != "scan":  # a load-test cell must not pass for a scanning one
            devices += f"; job profile {self.scfg.job_profile}: one view, no motion, no cut"
        return CellStatus(cell_id=self.cfg.cell_id, version=version(), mode=self.cfg.mode,
                          twin=MODES[self.cfg.mode].twin, scenes=list(SCENE_NAMES), arm_ready=rd.arm_ready,
                          camera_ready=rd.camera_ready, ready=rd.ready,
                          not_ready_reason=rd.reason[:1000] if rd.reason else None, devices=devices[:200],
                          accepting_jobs=accepting, queue_length=queue_length, queue_max=self.scfg.queue_max,
                          running_job=running.job_id if running else None, jobs_total=self.store.count(),
                          started_at=self.started_at, uptime_s=round(time.monotonic() - self._t0, 3))

    def paint(self) -> PaintReply:
        from cellctl.config import cell_planners_config

        p = cell_planners_config(self.cfg, self.cfg_path).paint
        return PaintReply(cell_id=self.cfg.cell_id, paint=PaintModel(name=p.name, lab_mean=list(p.lab_mean),
                                                                     source=p.source),
                          paint_file=str(self.cfg_path.parent / self.cfg.paint_file) if self.cfg.paint_file else None)

    def commission_paint(self, req: CommissionPaintRequest) -> CommissionPaintReply:
        """One picture of a sample, on the devices no job holds (the camera is the job's while it runs); every
        job queued after it finds the line by the new paint."""
        import base64

        from cellctl.scan.paint_sample import commission_and_write, picture, png_bytes
        from drivers.interfaces import DeviceError

        with self._cv:
            busy = self._running is not None or bool(self._queue)
        if busy or not self.devices.held.acquire(blocking=False):
            raise ApiError("cell_busy", "a job is running or queued, or the devices are being checked: commission "
                                        "the paint when the cell is idle")
        try:
            sample = {"finish": req.twin_finish, "paint": req.twin_paint, "light": req.twin_light,
                      "no_paint": req.twin_no_paint}
            try:
                run, out, done = commission_and_write(self.cfg, self.cfg_path, req.name, twin_sample=sample)
            except ValueError as e:
                raise ApiError("invalid_request", str(e)) from None
            except DeviceError as e:
                return CommissionPaintReply(ok=False, reason=f"no picture: {e}"[:1000])
        finally:
            self.devices.held.release()
        cal = run.calibration
        pic = base64.b64encode(png_bytes(picture(run)[::2, ::2])).decode()
        reply = CommissionPaintReply(ok=cal.ok, reason=cal.reason, delta_e=cal.delta_e, metal_lab=cal.metal_lab[:10],
                                     picture_png_base64=pic if len(pic) <= 700_000 else None)
        if cal.ok:
            self.cfg = self.cfg.model_copy(update={"paint_file": str(out.resolve())})  # the next job reads it
            reply.paint = PaintModel(name=cal.paint.name, lab_mean=list(cal.paint.lab_mean), source=cal.paint.source)
            log.info("paint %s commissioned by %s: %s (%s)", req.name, req.requested_by or "?", out,
                     done.get("config", ""))
        else:
            log.info("paint %s refused: %s", req.name, cal.reason)
        return reply

    def submit(self, req: ScanDrawingRequest) -> SubmitReply:
        with self._cv:  # the key's lookup and the job's creation under one lock: one key, one job
            if req.request_id is not None and (known := self.store.by_request_id(req.request_id)) is not None:
                return self._resubmitted(req, *known)  # before the checks: the job was accepted already
            self._check_scene(req.scene)
            if not self._accepting:
                raise ApiError("shutting_down", "the service is stopping and takes no new jobs")
            rd = self.devices.readiness()
            if not rd.ready:  # refused before anything is stored: the tablet keeps the job and submits again
                self.devices.poke()
                raise ApiError("cell_not_ready", f"the cell is not ready, nothing was queued: {rd.reason}; submit "
                               f"again once status shows ready (the devices are checked every "
                               f"{READINESS_PERIOD_S:g} s)"[:2000])
            if len(self._queue) >= self.scfg.queue_max:
                raise ApiError("queue_full", f"{len(self._queue)} jobs are waiting (service.queue_max = "
                               f"{self.scfg.queue_max}); submit again when one has started")
            job_id = new_job_id()
            while self.store.state(job_id) is not None:
                job_id = new_job_id()
            self.store.create(job_id, self.cfg.cell_id, req, str(self.job_dir(job_id)))
            self._queue.append(job_id)
            position = len(self._queue)
            # under the lock: the worker cannot start the job (and publish "scanning") before "queued"
            self.events.emit(job_id, "queued", "queued", max_steps=req.max_steps or self.default_max_steps)
            self._cv.notify()
        log.info("job %s queued (%s, %s, position %d)", job_id, req.scene, req.planner, position)
        return SubmitReply(job_id=job_id, queue_position=position)

    def _resubmitted(self, req: ScanDrawingRequest, job_id: str, first: ScanDrawingRequest, state: str) -> SubmitReply:
        """A submit whose request_id the cell holds: that job, whatever became of it (called under the lock)."""
        if req != first:
            raise ApiError("invalid_request", f"request_id {req.request_id!r} was used for job {job_id} with a "
                           f"different request; a new job needs a new request_id",
                           [_detail("request_id", "already used for a different request")])
        position = self._queue.index(job_id) + 1 if job_id in self._queue else None
        log.info("job %s submitted again (request_id %s): %s", job_id, req.request_id, state)
        return SubmitReply(job_id=job_id, state=state, queue_position=position, duplicate=True)

    def job(self, job_id: str):
        rec = self.store.get(job_id)
        if rec is None:
            raise ApiError("not_found", f"no job {job_id!r} on cell {self.cfg.cell_id}")
        return rec

    def _ended_folder(self, job_id: str) -> Path | None:
        """The folder of an ended job (None if it has none); not_found, or not_ended while it runs."""
        rec = self.job(job_id)
        if rec.state not in TERMINAL_STATES:
            raise ApiError("not_ended", f"job {job_id} is {rec.state}: its files are served once it has ended")
        return Path(rec.artifacts.dir) if rec.artifacts else None

    def list_jobs(self, req: ListJobsRequest) -> JobList:
        jobs, total = self.store.list(req.limit, req.state)
        return JobList(cell_id=self.cfg.cell_id, jobs=jobs, total=total, limit=req.limit)

    def cancel(self, job_id: str, req: CancelRequest) -> CancelReply:
        note = f"cancel requested{': ' + req.reason if req.reason else ''}"
        with self._cv:
            if self._running is not None and self._running.job_id == job_id:
                if self._running.request("operator"):
                    self.store.transition(job_id, "cancelling", note)
                    return CancelReply(job_id=job_id, state="cancelling")
                return CancelReply(job_id=job_id, state=self.store.state(job_id))  # already stopping
            if job_id in self._queue:
                self._queue.remove(job_id)
                self._finish(job_id, "cancelled", note)
                return CancelReply(job_id=job_id, state="cancelled")
            state = self.store.state(job_id)
        if state is None:
            raise ApiError("not_found", f"no job {job_id!r} on cell {self.cfg.cell_id}")
        raise ApiError("not_cancellable", f"job {job_id} already ended: {state}")

    def _check_scene(self, scene: str) -> str:
        """The scene to load: a built-in name, or the resolved path of a .yaml inside service.scene_dirs.
        A client may not make the cell read arbitrary files, nor learn which exist outside those directories:
        every path outside gets the same answer, whether or not it exists."""
        from sim.scenes import SCENE_NAMES

        if scene in SCENE_NAMES:
            return scene
        if not scene.endswith((".yaml", ".yml")):
            raise ApiError("invalid_request", f"scene: unknown scene {scene!r}; built-in: {', '.join(SCENE_NAMES)}",
                           [_detail("scene", "unknown scene")])
        allowed = ", ".join(str(d) for d in self.scene_dirs) or "none (service.scene_dirs is empty)"
        try:  # relative to the service's working directory, as the job would open it; symlinks followed
            path = Path(scene).resolve()
            inside = any(path.is_relative_to(d) for d in self.scene_dirs)
        except (OSError, RuntimeError, ValueError):  # a symlink loop, an unreadable component
            inside = False
        if not inside or not path.name.endswith((".yaml", ".yml")):
            raise ApiError("invalid_request", f"scene: {scene!r} is not a .yaml inside the cell's scene "
                           f"directories (service.scene_dirs: {allowed})"[:2000],
                           [_detail("scene", "not inside the allowed scene directories")])
        if not path.is_file():
            raise ApiError("invalid_request", f"scene: no scene file {scene!r} in the cell's scene directories "
                           f"({allowed})"[:2000], [_detail("scene", "no such scene file")])
        return str(path)

    # --- the worker -------------------------------------------------------------------------------
    def _work(self) -> None:
        self._prune()  # what a long stop may have left over the bounds
        try:
            self._job_worker.start()  # from this thread: the worker lives as long as it
        except Exception:  # noqa: BLE001 - each job tries again, and fails with the reason
            log.exception("the job worker did not start")
        while True:
            with self._cv:
                while not self._queue and not self._stopping.is_set():
                    self._cv.wait()
                if self._stopping.is_set():
                    return
                job_id = self._queue.popleft()
                ctl = self._running = JobControl(job_id)
                self.store.transition(job_id, "running")
            try:
                with self.devices.held:
                    self._run(ctl)
            except Exception:  # noqa: BLE001 - the worker must outlive any one job
                log.exception("job %s: the worker failed", job_id)
                self._finish(job_id, "failed", "internal error in the service", error="internal error; see the "
                             "service log")
            finally:
                with self._cv:
                    self._running = None
                self.devices.poke()  # the job may have found the arm or camera gone
                self._prune()

    def _run(self, ctl: JobControl) -> None:
        job_id = ctl.job_id
        rec = self.store.get(job_id)
        req = rec.request
        max_steps = req.max_steps or self.default_max_steps
        job_dir = self.job_dir(job_id)
        log.info("job %s running: %s with %s", job_id, req.scene, req.planner)
        self.events.emit(job_id, "scanning", "running", max_steps=max_steps, message="building the twin")

        def on_step(r: dict) -> None:
            self.events.emit(job_id, "scanning", self._state_of(ctl), step=r["step"],
                       coverage_percent=r["coverage_percent"], drawing_points=r["drawing_points"])

        def on_phase(phase: str) -> None:
            if phase == "planning-cut":
                self.events.emit(job_id, "planning-cut", self._state_of(ctl))

        timer = threading.Timer(self.scfg.job_timeout_s, ctl.request, ("timeout",))
        timer.daemon = True
        timer.start()
        summary, error, crashed = None, None, False
        try:
            scene = self._check_scene(req.scene)  # again: the file may have changed since the submit
            if not ctl.cancel.is_set():
                spec = JobSpec(self.cfg, self.cfg_path, scene, req.planner, profile=self.scfg.job_profile,
                               seed=req.seed, noise=req.noise, max_steps=req.max_steps, dry_run_cut=req.dry_run_cut,
                               run_dir=job_dir, arm_host=self.devices.arm_host,
                               record=self.scfg.record_jobs and self.scfg.job_profile == "scan")
                out = self._job_worker.run(spec, ctl.cancel, on_step=on_step, on_phase=on_phase,
                                           stopped_as=lambda: STOPPED_AS.get(ctl.reason, "cancelled"))
                summary, error, crashed = out.summary, out.error, out.crashed
                if crashed:
                    log.error("job %s: %s", job_id, error)
        except Exception as e:  # noqa: BLE001 - a failed job, not a failed service
            error = f"{type(e).__name__}: {e}"
            log.warning("job %s failed: %s", job_id, error)
        finally:
            timer.cancel()
        if summary is None:
            summary = summary_from_file(job_dir / "result.json")
        if ctl.reason == "shutdown":
            state, note, error = "interrupted", "the service was stopped", error or "interrupted: the service was stopped"
        elif ctl.reason == "timeout":
            state, note = "failed", f"timeout after {self.scfg.job_timeout_s:g} s"
            error = f"timeout: the job ran longer than service.job_timeout_s = {self.scfg.job_timeout_s:g} s"
        elif ctl.reason == "operator":
            state, note = "cancelled", "cancelled by the operator"
        elif crashed:
            state, note = "failed", "the job's worker process died"
        elif error:
            state, note = "failed", "the scan failed"
        else:
            state, note = "done", cut_warning(summary)
        self._finish(job_id, state, note, result=summary, error=error)

    def _prune(self) -> None:
        """Retention (cellctl.service.retention); a failure is logged, never a job's or the service's."""
        try:
            prune(self.store, self.data_dir / "jobs", max_age_days=self.scfg.retention_days,
                  max_gb=self.scfg.retention_gb)
        except Exception:  # noqa: BLE001 - the disk's housekeeping must not stop the cell
            log.exception("retention failed")

    def _state_of(self, ctl: JobControl) -> str:
        return "cancelling" if ctl.cancel.is_set() and ctl.reason == "operator" else "running"

    def _finish(self, job_id: str, state: str, note: str | None, *, result: ResultSummary | None = None,
                error: str | None = None) -> None:
        """The terminal transition, then its event (a client seeing the event finds the record final)."""
        d = self.job_dir(job_id)
        files = sorted(p.name for p in d.iterdir() if p.is_file()) if d.is_dir() else []
        with self._cv:  # with the record final, the job is no longer the running one (cancel, status)
            try:
                self.store.transition(job_id, state, note, result=result, error=error,
                                      artifacts=Artifacts(dir=str(d), files=files[:100]))
            except StoreError as e:  # already ended (e.g. marked interrupted by a stop that gave up waiting)
                log.warning("%s", e)
                return
            finally:
                if self._running is not None and self._running.job_id == job_id:
                    self._running = None
        last = result.coverage_percent if result is not None else None
        self.events.emit(job_id, state, state, coverage_percent=last, message=(error or note or "")[:2000] or None)
        log.info("job %s %s%s", job_id, state, f": {error.splitlines()[0]}" if error else "")


def cut_warning(summary: ResultSummary | None) -> str | None:
    """A done job whose line is not all cut says so in its final note and event, in words."""
    cut = summary.cut if summary is not None else None
    if cut is None:
        return None
    if cut.error:
        return f"warning: no cut: {cut.error}"[:500]
    if cut.feasible_branches == 0:
        return ("warning: nothing on the drawing can be cut" + (f": {cut.warnings[-1]}" if cut.warnings else ""))[:500]
    uncut = {}
    for g in cut.gaps:
        if g.length_m > 0:
            uncut[g.reason] = uncut.get(g.reason, 0.0) + g.length_m
    if cut.paint is not None:  # what the paint says, not the cut's own line
        uncut = {}
        for u in cut.paint.uncut:
            uncut[u.reason] = uncut.get(u.reason, 0.0) + u.length_m
    unseen = cut.paint.unseen if cut.paint is not None else []
    if cut.told_share >= 0.999 and not uncut and not unseen:
        return None
    parts = ", ".join(f"{1000 * v:.0f} mm {k}" for k, v in sorted(uncut.items()))
    return (f"warning: {100 * cut.told_share:.1f} % of the drawing will be cut in {cut.feasible_branches} cuts"
            + (f"; uncut: {parts}" if parts else "")
            + (f"; the paint runs on unseen at {len(unseen)} border{'s' if len(unseen) > 1 else ''}: the share is "
               "of the paint seen" if unseen else ""))[:500]


def _detail(loc: str, msg: str):
    from cellctl.service.api import ErrorDetail

    return ErrorDetail(loc=loc, msg=msg)


# --- `cellctl serve` ------------------------------------------------------------------------------
def serve(cfg: CellConfig, cfg_path: Path, data_dir: str | None = None, *, listen: list[str] | None = None,
          connect: list[str] | None = None) -> int:
    """Run until SIGINT/SIGTERM; the running job is cancelled (interrupted) and the Zenoh session
    closed on every way out."""
    logs.setup()
    stop = threading.Event()

    def on_signal(signum, _frame):
        if stop.is_set():
            log.warning("second %s: exiting without waiting for the job", signal.Signals(signum).name)
            raise KeyboardInterrupt
        log.info("%s: stopping", signal.Signals(signum).name)
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    svc = CellService(cfg, cfg_path, data_dir, listen=listen, connect=connect)
    try:
        try:
            svc.start()
        except ServiceError as e:
            print(f"cellctl serve: {e}", file=sys.stderr)
            return 1
        except CellUnreachable as e:  # client of a router: certificates, password or no router, said apart
            print(f"cellctl serve: cannot join the yard network: {e}", file=sys.stderr)
            return 1
        except zenoh.ZError as e:
            eps = ", ".join(svc.listen if cfg.service.zenoh_mode == "peer" else svc.connect)
            print(f"cellctl serve: cannot open the Zenoh session ({cfg.service.zenoh_mode} on {eps}): "
                  f"{zenoh_error(e)}",
                  file=sys.stderr)
            return 1
        how = (f"listening on {', '.join(svc.listen)}" if cfg.service.zenoh_mode == "peer" and svc.listen
               else f"client of {', '.join(svc.connect)}")
        print(f"cell {cfg.cell_id}: serving cell/{cfg.cell_id}/** ({how}); data in {svc.data_dir}; pid {os.getpid()}",
              flush=True)
        while not stop.wait(0.5):
            pass
        svc.stop()
        return 0
    except KeyboardInterrupt:
        return 130
    finally:
        svc.close()
        for s, h in old.items():
            signal.signal(s, h)
        log.info("stopped")

