"""The cells on the yard network as the tablet sees them: one Zenoh session, kept open (and opened again
when it loses its router or cell), the cells found by their liveliness tokens, each cell's status and
the latest event of every job. A background thread keeps it fresh; pages read snapshots and never wait
on the network."""

from __future__ import annotations

import logging
import re
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import zenoh
from pydantic import ValidationError

from cellctl.service.api import CELL_ID_PATTERN, CellStatus, JobEvent
from cellctl.service.client import CellClient, CellError, CellUnreachable, NoReply, open_session, zenoh_error
from cellctl.tablet.config import TabletConfig

log = logging.getLogger("cellctl.tablet.yard")
ALIVE_KEYS = "cell/*/alive"
EVENT_KEYS = "cell/*/jobs/*/events"
LOST_AFTER_S = 3.0  # no router or peer this long: the session is opened again
KEEP_EVENTS = 500


@dataclass(frozen=True)
class CellView:
    cell_id: str
    online: bool  # its liveliness token is there
    status: CellStatus | None  # the last status read (None: never read)
    error: str | None  # why the last read failed
    seen_at: float | None  # time.time() of the last status read


class Yard:
    def __init__(self, cfg: TabletConfig):
        self.cfg = cfg
        self._lock = threading.Lock()
        self._session: zenoh.Session | None = None
        self._sub = None
        self._cells: dict[str, CellView] = {}
        self._events: dict[str, JobEvent] = {}
        self._problem: str | None = "connecting to the cell network"
        self._lost_since: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="tablet-yard", daemon=True)
        self._pool = ThreadPoolExecutor(max_workers=8, thread_name_prefix="tablet-status")

    # --- what pages read ----------------------------------------------------------------------------
    @property
    def problem(self) -> str | None:
        """None while the session reaches the network; else why not, in words for the operator."""
        return self._problem

    def cells(self) -> list[CellView]:
        with self._lock:
            return sorted(self._cells.values(), key=lambda c: c.cell_id)

    def cell(self, cell_id: str) -> CellView | None:
        with self._lock:
            return self._cells.get(cell_id)

    def last_event(self, job_id: str) -> JobEvent | None:
        with self._lock:
            return self._events.get(job_id)

    def client(self, cell_id: str) -> CellClient:
        """A client of one cell on the app's session (cheap: no session of its own)."""
        s = self._session
        if s is None:
            raise CellUnreachable(self._problem or "not connected to the cell network")
        return CellClient(cell_id, self.cfg.connect, timeout_s=self.cfg.query_timeout_s, session=s)

    # --- life ---------------------------------------------------------------------------------------
    def start(self) -> Yard:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._close()

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                self._tick()
            except Exception as e:  # noqa: BLE001 - the app must outlive any one bad reply
                log.exception("yard refresh failed")
                self._problem = f"cell network: {e}"
            self._stop.wait(max(0.05, self.cfg.refresh_s - (time.monotonic() - t0)))

    def _tick(self) -> None:
        if self._session is None and not self._open():
            return
        if not self._connected():
            return
        found = self._alive_cells()
        with self._lock:
            known = set(self._cells) | found
        views = list(self._pool.map(lambda cid: self._read(cid, cid in found), sorted(known)))
        with self._lock:
            for v in views:
                self._cells[v.cell_id] = v

    def _open(self) -> bool:
        try:
            self._session = open_session(self.cfg.connect, mode=self.cfg.zenoh_mode,
                                         zenoh_config_file=str(self.cfg.zenoh_config) if self.cfg.zenoh_config
                                         else None, tls_ca=self.cfg.tls_ca)
        except (CellUnreachable, ValueError) as e:
            self._problem = str(e)
            return False
        self._sub = self._session.declare_subscriber(EVENT_KEYS, self._on_event)
        self._lost_since, self._problem = None, None
        log.info("connected to the cell network at %s", ", ".join(self.cfg.connect))
        return True

    def _close(self) -> None:
        s, self._session = self._session, None
        if s is not None:
            try:
                s.close()
            except Exception:  # noqa: BLE001 - already gone
                pass

    def _connected(self) -> bool:
        """A client session needs its router (or the cell it connects to); lost for LOST_AFTER_S, it is
        closed and opened again, as docs/API.md advises."""
        info = self._session.info
        if self.cfg.zenoh_mode == "peer" or list(info.routers_zid()) or list(info.peers_zid()):
            self._lost_since, self._problem = None, None
            return True
        now = time.monotonic()
        self._lost_since = self._lost_since or now
        self._problem = f"lost the connection to the cell network at {', '.join(self.cfg.connect)}; reconnecting"
        if now - self._lost_since > LOST_AFTER_S:
            self._close()
            with self._lock:  # every cell is unknown until the network answers again
                self._cells = {k: CellView(k, False, v.status, "no connection", v.seen_at)
                               for k, v in self._cells.items()}
        return False

    def _alive_cells(self) -> set[str]:
        found = set()
        for r in self._session.liveliness().get(ALIVE_KEYS, timeout=self.cfg.query_timeout_s):
            if r.ok is not None:
                parts = str(r.ok.key_expr).split("/")
                if len(parts) == 3 and re.match(CELL_ID_PATTERN, parts[1]):
                    found.add(parts[1])
        return found

    def _read(self, cell_id: str, online: bool) -> CellView:
        prev = self.cell(cell_id)
        try:
            st = self.client(cell_id).status(timeout_s=self.cfg.query_timeout_s)
            return CellView(cell_id, online, st, None, time.time())
        except (NoReply, CellError, CellUnreachable) as e:
            why = "offline: no reply" if isinstance(e, NoReply) else str(e)
            return CellView(cell_id, online, prev.status if prev else None, why, prev.seen_at if prev else None)
        except zenoh.ZError as e:
            return CellView(cell_id, False, prev.status if prev else None, zenoh_error(e),
                            prev.seen_at if prev else None)

    def _on_event(self, sample: zenoh.Sample) -> None:
        try:
            ev = JobEvent.model_validate_json(sample.payload.to_bytes())
        except ValidationError:
            return
        with self._lock:
            old = self._events.get(ev.job_id)
            if old is None or ev.seq >= old.seq:
                self._events[ev.job_id] = ev
            if len(self._events) > KEEP_EVENTS:
                for k in sorted(self._events)[: len(self._events) - KEEP_EVENTS]:
                    del self._events[k]
