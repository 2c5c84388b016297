"""The tablet's pages (NiceGUI): log in, the cells, one cell (start a scan, its jobs), one job (live
progress, cancel, what will be cut, the 3-D view). Big touch targets, dark text on white for daylight.

Pages read the Yard's snapshots on a timer and never wait on Zenoh in the event loop: every query runs
in a worker thread (``run.io_bound``). Every command checks the logged-in role on the server."""

from __future__ import annotations

import asyncio
from pathlib import Path

from fastapi.responses import RedirectResponse
from nicegui import app, run, ui

from cellctl.service.api import (PLANNER_NAMES, TERMINAL_STATES, CommissionPaintRequest, JobRecord,
                                 ScanDrawingRequest)
from cellctl.service.client import CellError, CellUnreachable, NoReply
from cellctl.tablet import geometry, words
from cellctl.tablet.accounts import AccountBook
from cellctl.tablet.config import TabletConfig
from cellctl.tablet.yard import CellView, Yard
from planners.registry import DEFAULT_PLANNER

BIG = "text-xl px-6 py-3 min-h-[3.5rem]"  # a gloved finger's target
CSS = """
body { font-size: 19px; color: #111; background: #fff; }
.q-field__native, .q-field__label, .q-item__label { font-size: 19px !important; }
.cell-card { min-width: 19rem; cursor: pointer; border: 2px solid #ccc; }
"""
NET_ERRORS = (CellError, NoReply, CellUnreachable, TimeoutError)


def _say(e: Exception) -> str:
    if isinstance(e, NoReply):
        return "The cell did not answer: it is down, or this account may not do that."
    if isinstance(e, CellError):
        return e.message
    return str(e)


def register(cfg: TabletConfig, yard: Yard, accounts: AccountBook) -> None:
    def _who() -> tuple[str, str] | None:
        """The logged-in user and role, if that login still exists with that role (it may have been removed:
        a lost tablet); a login that ended is logged out here."""
        u = app.storage.user
        if not (u.get("user") and u.get("role")):
            return None
        acct = accounts.lookup(u["user"])
        if acct is None or acct.role != u["role"]:
            u.clear()
            return None
        return acct.user, acct.role

    def _may_command() -> bool:
        who = _who()
        return who is not None and who[1] == "operator"

    def frame(title: str) -> RedirectResponse | None:
        """Header and the network banner; a redirect to /login (answered by the server, before any page is
        built) when nobody is logged in."""
        who = _who()
        if who is None:
            return RedirectResponse("/login")
        ui.add_css(CSS)
        ui.page_title(f"{cfg.title}: {title}")
        with ui.header().classes("bg-grey-10 items-center q-px-md"):
            ui.button(icon="home", on_click=lambda: ui.navigate.to("/")).props("flat color=white size=lg") \
                .props('data-testid=home aria-label="all cells"')
            ui.label(title).classes("text-2xl font-bold")
            ui.space()
            ui.label(f"{who[0]} ({who[1]})").classes("text-lg").props("data-testid=who")
            ui.button("Log out", on_click=_logout).props("flat color=white").classes("text-lg")
        banner = ui.label().classes("w-full text-xl font-bold bg-red-9 text-white q-pa-md") \
            .props("data-testid=network")

        def show_network():
            if _who() is None:  # the login was removed or changed while the page was open
                ui.navigate.to("/login")
                return
            banner.text = yard.problem or ""
            banner.set_visibility(bool(yard.problem))

        show_network()
        ui.timer(1.0, show_network)
        return None

    def _logout():
        app.storage.user.clear()
        ui.navigate.to("/login")

    @ui.page("/login")
    def login_page():
        ui.add_css(CSS)
        ui.page_title(f"{cfg.title}: log in")

        async def try_login():
            acct = await run.io_bound(accounts.check, user.value or "", password.value or "")
            if acct is None:
                await asyncio.sleep(1.0)  # a guesser waits too
                error.text = "Wrong user or password."
                return
            app.storage.user.update({"user": acct.user, "role": acct.role})
            ui.navigate.to("/")

        with ui.card().classes("absolute-center w-[26rem] q-pa-lg"):
            ui.label(cfg.title).classes("text-3xl font-bold")
            ui.label("Log in to the cutting cells").classes("text-lg")
            user = ui.input("User").classes("w-full").props("data-testid=user autocomplete=username")
            password = ui.input("Password", password=True).classes("w-full") \
                .props("data-testid=password autocomplete=current-password").on("keydown.enter", try_login)
            ui.button("Log in", on_click=try_login).classes(f"w-full {BIG}").props("data-testid=login")
            error = ui.label().classes("text-red-9 text-lg").props("data-testid=login-error")

    # --- all cells -----------------------------------------------------------------------------------
    @ui.page("/")
    def cells_page():
        if (login := frame("Cells")) is not None:
            return login
        empty = ui.label("No cell found on the network yet.").classes("text-xl q-pa-md")
        row = ui.row().classes("q-pa-md gap-6")
        cards: dict[str, CellCard] = {}

        def refresh():
            """Cards are made once and their text changed in place: a card redrawn under a finger would
            lose the tap."""
            cells = yard.cells()
            empty.set_visibility(not cells)
            for c in cells:
                if c.cell_id not in cards:
                    with row:
                        cards[c.cell_id] = CellCard(c.cell_id)
                cards[c.cell_id].show(c)

        refresh()
        ui.timer(cfg.refresh_s, refresh)

    def _card_key(c: CellView):
        s = c.status
        return (c.cell_id, c.online, c.error, s and (s.ready, s.not_ready_reason, s.running_job, s.queue_length))

    class CellCard:
        """One cell's card: its lines are labels whose text and colour change, never new elements."""

        LINES = 4

        def __init__(self, cell_id: str) -> None:
            with ui.card().classes("cell-card q-pa-lg").props(f"data-testid=cell-{cell_id}") \
                    .on("click", lambda _=None: ui.navigate.to(f"/cell/{cell_id}")):
                ui.label(cell_id).classes("text-3xl font-bold")
                self.lines = [ui.label().classes("text-xl") for _ in range(self.LINES)]
                self.devices = ui.label().classes("text-base text-grey-8")
            self._colours = [""] * self.LINES

        def show(self, c: CellView) -> None:
            lines = _cell_lines(c)
            for k, label in enumerate(self.lines):
                text, colour = lines[k] if k < len(lines) else ("", "")
                label.text = text
                if colour != self._colours[k]:
                    label.classes(remove=f"text-{self._colours[k]}" if self._colours[k] else None,
                                  add=f"text-{colour}" if colour else None)
                    self._colours[k] = colour
                label.set_visibility(bool(text))
            self.devices.text = f"{c.status.devices} ({c.status.mode})" if c.status is not None else ""

    def _cell_lines(c: CellView) -> list[tuple[str, str]]:
        s = c.status
        if not c.online or c.error or s is None:
            return [("Offline" + (f": {c.error}" if c.error else ""), "red-9")]
        lines = [("Online", "green-9")]
        lines.append(("Ready" if s.ready else f"Not ready: {s.not_ready_reason or 'unknown'}",
                      "green-9" if s.ready else "red-9"))
        lines.append((f"Busy: job {s.running_job}" if s.running_job else "Idle", "blue-9" if s.running_job else "grey-9"))
        lines.append((f"Queue: {s.queue_length} waiting", "grey-9"))
        return lines

    # --- one cell ------------------------------------------------------------------------------------
    @ui.page("/cell/{cell_id}")
    def cell_page(cell_id: str):
        if (login := frame(f"Cell {cell_id}")) is not None:
            return login
        shown: list = [None, None]

        @ui.refreshable
        def state():
            c = yard.cell(cell_id)
            with ui.row().classes("q-px-md gap-8 items-center"):
                if c is None:
                    ui.label("This cell has not been seen on the network.").classes("text-xl text-red-9")
                    return
                for text, colour in _cell_lines(c):
                    ui.label(text).classes(f"text-xl text-{colour}").props("data-testid=cell-state")
                if c.status and c.status.running_job:
                    ui.button("Watch the running job", on_click=lambda j=c.status.running_job:
                              ui.navigate.to(f"/cell/{cell_id}/job/{j}")).classes(BIG).props("data-testid=running")

        @ui.refreshable
        def start_form():
            c = yard.cell(cell_id)
            twin = bool(c and c.status and c.status.twin)
            scenes = c.status.scenes if twin else []
            with ui.card().classes("q-ma-md q-pa-lg w-[40rem] max-w-full"):
                ui.label("Scan drawing").classes("text-2xl font-bold")
                ui.label("The arm explores the piece, finds the painted line and plans the cut.").classes("text-lg")
                planner = ui.select(list(PLANNER_NAMES), value=DEFAULT_PLANNER, label="Planner") \
                    .classes("w-full text-xl").props("data-testid=planner")
                scene = None
                if scenes:
                    scene = ui.select(scenes, value=scenes[0], label="Piece (twin cell)") \
                        .classes("w-full").props("data-testid=scene")
                if not _may_command():
                    ui.label("You are logged in as a viewer: you can watch, not start or cancel.") \
                        .classes("text-lg text-orange-10").props("data-testid=viewer-note")
                    return
                if not twin and cfg.real_scene is None:
                    ui.label("Set real_scene in the tablet config (the scene file that gives this cell's "
                             "initial views) to start jobs on it.").classes("text-lg text-red-9")
                    return

                async def start():
                    if not _may_command():  # the page may be stale; the role is checked here, on the server
                        ui.notify("Only an operator can start a scan.", type="negative")
                        return
                    req = ScanDrawingRequest(scene=scene.value if scene else cfg.real_scene, planner=planner.value,
                                             requested_by=_who()[0])
                    button.disable()
                    try:
                        reply = await run.io_bound(lambda: yard.client(cell_id).submit(req))
                    except NET_ERRORS as e:
                        ui.notify(f"Not started: {_say(e)}", type="negative", timeout=10000, multi_line=True)
                        button.enable()
                        return
                    ui.navigate.to(f"/cell/{cell_id}/job/{reply.job_id}")

                button = ui.button("Start scan", icon="play_arrow", on_click=start) \
                    .classes(f"w-full {BIG} text-2xl").props("color=green-9 data-testid=start")

        @ui.refreshable
        def history():
            ui.label("Jobs").classes("text-2xl font-bold q-px-md")
            jobs = shown[1]
            if jobs is None:
                ui.label("Reading the cell's jobs...").classes("q-px-md")
                return
            if isinstance(jobs, str):
                ui.label(jobs).classes("q-px-md text-red-9")
                return
            if not jobs.jobs:
                ui.label("No jobs on this cell yet.").classes("q-px-md text-lg").props("data-testid=no-jobs")
                return
            with ui.column().classes("q-px-md w-full gap-2"):
                for j in jobs.jobs:
                    with ui.row().classes("items-center gap-4 w-full border-b q-py-sm cursor-pointer") \
                            .props(f"data-testid=job-{j.job_id}") \
                            .on("click", lambda _=None, jid=j.job_id: ui.navigate.to(f"/cell/{cell_id}/job/{jid}")):
                        ui.badge(j.state, color=words.STATE_COLOURS.get(j.state, "grey")).classes("text-lg")
                        ui.label(words.when(j.created_at)).classes("text-lg")
                        ui.label(f"{j.scene}, {j.planner}").classes("text-lg")
                        if j.coverage_percent is not None:
                            ui.label(f"{j.coverage_percent:.1f} % seen").classes("text-lg")
                        if j.error:
                            ui.label(j.error).classes("text-red-9")

        async def load_jobs():
            try:
                jobs = await run.io_bound(lambda: yard.client(cell_id).jobs(limit=30))
            except NET_ERRORS as e:
                jobs = f"Cannot read the jobs: {_say(e)}"
            if jobs != shown[1]:  # redrawn only when it changed: a row redrawn under a finger loses the tap
                shown[1] = jobs
                history.refresh()

        last = [None, None]

        async def refresh():
            c = yard.cell(cell_id)
            key = _card_key(c) if c else None
            if key != last[0]:
                last[0] = key
                state.refresh()
            mode = (c.status.twin, tuple(c.status.scenes)) if c and c.status else None
            if mode != last[1]:
                last[1] = mode
                start_form.refresh()
            total = c.status.jobs_total if c and c.status else None
            if total is not None and total != shown[0]:
                shown[0] = total
                await load_jobs()

        def paint_card():
            """The paint the cell looks for, and (operators) commissioning a new one from a sample in front of
            the camera. Built once: a form redrawn under a finger loses the tap."""
            c = yard.cell(cell_id)
            twin = bool(c and c.status and c.status.twin)
            with ui.card().classes("q-ma-md q-pa-lg w-[40rem] max-w-full").props("data-testid=paint-card"):
                ui.label("The yard's paint").classes("text-2xl font-bold")
                now = ui.label("Reading the cell's paint...").classes("text-xl").props("data-testid=paint-now")

                async def load():
                    try:
                        r = await run.io_bound(lambda: yard.client(cell_id).paint())
                        now.text = f"This cell finds lines of {r.paint.name} paint ({r.paint.source})."
                    except NET_ERRORS as e:
                        now.text = f"Cannot read the cell's paint: {_say(e)}"

                ui.timer(0.1, load, once=True)
                if not _may_command():
                    return
                ui.label("To change it: spray a patch of the new paint on a piece of the yard's scrap, hold it "
                         "0.3-0.5 m in front of the camera, the paint in the middle of the picture and bare metal "
                         "all round it.").classes("text-lg")
                name = ui.input("Paint name (e.g. pink)").classes("w-full text-xl").props("data-testid=paint-name")
                sample = {}
                if twin:
                    with ui.row().classes("w-full gap-4"):
                        sample["twin_finish"] = ui.input("Sample metal (twin)", value="rust_red") \
                            .props("data-testid=paint-finish")
                        sample["twin_paint"] = ui.input("Sample paint (twin, default the name)") \
                            .props("data-testid=paint-colour")
                        sample["twin_light"] = ui.input("Light (twin)", value="normal")
                told = ui.column().classes("w-full").props("data-testid=paint-result")

                async def commission():
                    if not _may_command():
                        ui.notify("Only an operator can commission the paint.", type="negative")
                        return
                    req = {"name": (name.value or "").strip(), "requested_by": _who()[0],
                           **{k: (v.value or "").strip() or None for k, v in sample.items()}}
                    try:
                        req = CommissionPaintRequest.model_validate(req)
                    except ValueError:
                        ui.notify("Give the paint a name: letters, digits, spaces or dashes.", type="negative")
                        return
                    button.disable()
                    told.clear()
                    with told:
                        ui.label("Taking the picture...").classes("text-lg")
                    try:
                        reply = await run.io_bound(lambda: yard.client(cell_id).commission_paint(req))
                    except NET_ERRORS as e:
                        reply = None
                        told.clear()
                        with told:
                            ui.label(f"Not commissioned: {_say(e)}").classes("text-lg text-red-9")
                    button.enable()
                    if reply is None:
                        return
                    told.clear()
                    with told:
                        if reply.ok:
                            ui.label(f"Commissioned: the cell now finds lines of {reply.paint.name} paint "
                                     f"(ΔE {reply.delta_e:.0f} from the metal).").classes("text-lg text-green-9") \
                                .props("data-testid=paint-ok")
                        else:
                            ui.label(f"Refused, the paint is unchanged: {reply.reason}").classes(
                                "text-lg text-red-9").props("data-testid=paint-refused")
                        if reply.picture_png_base64:
                            ui.image("data:image/png;base64," + reply.picture_png_base64).classes("w-[424px]") \
                                .props("data-testid=paint-picture")
                            ui.label("Cyan: what the cell takes as paint").classes("text-lg")
                    await load()

                button = ui.button("Commission paint", icon="palette", on_click=commission).classes(BIG) \
                    .props("color=blue-9 data-testid=commission")

        c0 = yard.cell(cell_id)
        last[:] = [_card_key(c0) if c0 else None, (c0.status.twin, tuple(c0.status.scenes)) if c0 and c0.status
                   else None]
        state()
        start_form()
        paint_card()
        history()
        ui.timer(cfg.refresh_s, refresh)
        ui.timer(5.0, load_jobs)  # states of listed jobs change without the total changing

    # --- one job -------------------------------------------------------------------------------------
    @ui.page("/cell/{cell_id}/job/{job_id}")
    async def job_page(cell_id: str, job_id: str):
        if (login := frame(f"Cell {cell_id}: job {job_id}")) is not None:
            return login
        rec: list[JobRecord | None] = [None]
        err: list[str | None] = [None]

        async def read() -> None:
            try:
                rec[0], err[0] = await run.io_bound(lambda: yard.client(cell_id).job(job_id)), None
            except NET_ERRORS as e:
                err[0] = f"Cannot read the job: {_say(e)}"

        @ui.refreshable
        def head():
            r = rec[0]
            if r is None:
                ui.label(err[0] or "Reading the job...").classes("text-xl q-pa-md text-red-9")
                return
            with ui.row().classes("q-pa-md items-center gap-6"):
                ui.badge(r.state, color=words.STATE_COLOURS.get(r.state, "grey")).classes("text-2xl q-pa-sm") \
                    .props("data-testid=job-state")
                ui.label(f"{r.request.scene}, planner {r.request.planner}").classes("text-xl")
                ui.label(f"started {words.when(r.created_at)}"
                         + (f" by {r.request.requested_by}" if r.request.requested_by else "")).classes("text-lg")

        @ui.refreshable
        def live():
            r = rec[0]
            if r is None or r.state in TERMINAL_STATES:
                return
            ev = yard.last_event(job_id)
            phase = ev.phase if ev else (r.progress.phase if r.progress else "queued")
            step = ev.step if ev else (r.progress.step if r.progress else None)
            n = ev.max_steps if ev else (r.progress.max_steps if r.progress else None)
            cov = ev.coverage_percent if ev else (r.progress.coverage_percent if r.progress else None)
            with ui.card().classes("q-ma-md q-pa-lg w-[40rem] max-w-full"):
                ui.label(words.PHASES.get(phase, phase)).classes("text-3xl font-bold").props("data-testid=phase")
                if step is not None:
                    ui.label(f"View {step + 1}" + (f" of at most {n}" if n else "")).classes("text-xl") \
                        .props("data-testid=step")
                if cov is not None:
                    ui.label(f"Drawing seen so far: {cov:.1f} %").classes("text-xl").props("data-testid=coverage")
                    ui.linear_progress(cov / 100, show_value=False, size="16px").props("color=blue-8")
                ui.label(f"Running for {words.elapsed(r)}").classes("text-xl").props("data-testid=elapsed")
                if ev and ev.message:
                    ui.label(ev.message).classes("text-lg text-grey-9")

        async def cancel():
            if not _may_command():
                ui.notify("Only an operator can cancel a job.", type="negative")
                return
            reason = f"tablet: {_who()[0]}"  # the login is read here, in the page's context, not in the worker thread
            cancel_button.disable()
            try:
                reply = await run.io_bound(lambda: yard.client(cell_id).cancel(job_id, reason=reason))
                ui.notify(f"Job {reply.state}.", type="info")
            except NET_ERRORS as e:
                ui.notify(f"Not cancelled: {_say(e)}", type="negative", timeout=10000)
            cancel_button.enable()
            await read()
            head.refresh()
            live.refresh()
            show_cancel()

        def show_cancel() -> None:
            r = rec[0]
            if cancel_button is not None:
                cancel_button.set_visibility(bool(r is not None and r.state not in TERMINAL_STATES
                                                  and r.state != "cancelling" and _may_command()))

        @ui.refreshable
        def result():
            r = rec[0]
            if r is None or r.state not in TERMINAL_STATES:
                return
            if r.error:
                ui.label(f"Error: {r.error}").classes("text-xl text-red-9 q-px-md").props("data-testid=job-error")
            paint_box = ui.column().classes("q-ma-md w-full").props("data-testid=paint-views")
            asyncio.get_event_loop().create_task(fill_paint(paint_box))
            s = r.result
            if s is None:
                return
            row = ui.row().classes("w-full items-start")
            with row, ui.card().classes("q-ma-md q-pa-lg w-[32rem] max-w-full").props("data-testid=cut-summary"):
                ui.label("What will be cut").classes("text-2xl font-bold")
                cut = s.cut
                if cut is None:
                    ui.label("No cut was planned.").classes("text-xl text-red-9")
                else:
                    ui.label(f"{100 * cut.told_share:.0f} % of the {100 * cut.told_length_m:.0f} cm line will "
                             f"be cut").classes("text-2xl").props("data-testid=cut-fraction")
                    ui.label(f"{cut.feasible_branches} cut{'s' if cut.feasible_branches != 1 else ''}"
                             + (f" ({cut.branches - cut.feasible_branches} the arm cannot run)"
                                if cut.branches > cut.feasible_branches else "")).classes("text-xl") \
                        .props("data-testid=cuts")
                    gaps = [g for g in cut.gaps if g.length_m > 0]
                    if gaps:
                        ui.label("Left uncut:").classes("text-xl font-bold q-mt-sm")
                        for g in gaps:
                            ui.label(f"{1000 * g.length_m:.0f} mm: {words.gap_reason(g.reason)}"
                                     + (f": {g.detail}" if g.detail else "")).classes("text-lg") \
                                .props("data-testid=gap")
                    for w in cut.warnings:
                        ui.label(f"Note: {w}").classes("text-lg text-orange-10").props("data-testid=warning")
                    if cut.error:
                        ui.label(cut.error).classes("text-lg text-red-9")
                ui.label(f"Scan: {s.coverage_percent:.1f} % of the line seen in {s.steps} views; stopped at "
                         f"{words.STOPPED_BY.get(s.terminated_by, s.terminated_by)}.").classes("text-lg q-mt-sm") \
                    .props("data-testid=scan-line")
            with row:
                view3d()

        @ui.refreshable
        def view3d():
            r = rec[0]
            if r is None or r.state not in TERMINAL_STATES:
                return
            box = ui.column().classes("q-ma-md").props("data-testid=view3d")
            with box:
                ui.label("Fetching the 3-D view...").classes("text-lg")
            asyncio.get_event_loop().create_task(fill_3d(box))

        async def fill_paint(box):
            """Every view's camera picture, what the cell took as paint in cyan: where an operator sees
            that rust or a stray mark was taken for the line before the torch is lit."""
            cache = Path(cfg.state_dir) / "jobs" / cell_id / job_id
            try:
                pictures = await run.io_bound(lambda: geometry.paint_pictures(yard.client(cell_id), job_id, cache))
            except (*NET_ERRORS, OSError, ValueError) as e:
                box.clear()
                with box:
                    ui.label(f"No paint pictures: {_say(e)}").classes("text-lg text-red-9")
                return
            box.clear()
            if not pictures:
                return
            with box:
                ui.label("What the camera took as paint (cyan)").classes("text-2xl font-bold")
                with ui.row().classes("gap-3"):
                    for caption, path in pictures:
                        with ui.column().classes("gap-1"):
                            ui.image(str(path)).classes("w-[320px]").props(f"data-testid=paint-{path.stem}")
                            ui.label(caption).classes("text-lg")

        async def fill_3d(box):
            cache = Path(cfg.state_dir) / "jobs" / cell_id / job_id
            try:
                files = await run.io_bound(lambda: geometry.fetch(yard.client(cell_id), job_id, cache))
                g = await run.io_bound(geometry.load, files, cfg.max_points)
            except (*NET_ERRORS, OSError, ValueError) as e:
                box.clear()
                with box:
                    ui.label(f"No 3-D view: {_say(e)}").classes("text-lg text-red-9")
                return
            box.clear()
            with box:
                _scene(g)

        shown: list = [None, None]  # the state and the live figures on screen

        async def tick():
            r, ev = rec[0], yard.last_event(job_id)
            if r is None or (ev is not None and ev.phase in TERMINAL_STATES and r.state not in TERMINAL_STATES):
                await read()
            r = rec[0]
            if r is not None and r.state != shown[0]:
                shown[0] = r.state
                head.refresh()
                result.refresh()
            figures = (r and r.state, ev and ev.seq, words.elapsed(r))
            if figures != shown[1]:
                shown[1] = figures
                live.refresh()
            show_cancel()

        await read()
        shown[0] = rec[0].state if rec[0] else None
        head()
        live()
        # made once, beside the live figures that are redrawn every second: a button redrawn under a
        # finger loses the tap (the click names an element the server has already replaced)
        cancel_button = None
        if _may_command():  # a viewer's page has none
            cancel_button = ui.button("Cancel job", icon="stop", on_click=cancel).classes(f"{BIG} q-mx-md") \
                .props("color=red-9 data-testid=cancel")
        show_cancel()
        result()
        ui.timer(1.0, tick)
        ui.timer(5.0, read)  # an event may be lost: the record is the truth

    def _scene(g: geometry.JobGeometry):
        centre, radius = g.frame()
        with ui.row().classes("gap-4 text-lg"):
            ui.label("Red: the drawing").classes("text-red-9")
            ui.label("Blue: the cut").classes("text-blue-9")
            ui.label("Orange: torch axis").classes("text-orange-9")
            ui.label("Magenta: left uncut").classes("text-purple-9")
        with ui.scene(width=600, height=500, grid=False, background_color="#f4f4f4") as sc:
            if len(g.surface):
                sc.point_cloud(g.surface.tolist(), (0.1 + 0.5 * g.surface_rgb).tolist(), point_size=0.005)
            if len(g.drawing):
                sc.point_cloud(g.drawing.tolist(), [[0.85, 0.05, 0.05]] * len(g.drawing), point_size=0.006)
            for pts in g.cuts:
                _polyline(sc, pts, "#1565c0")
                sc.point_cloud(pts.tolist(), [[0.05, 0.25, 0.8]] * len(pts), point_size=0.012)
            for pts in g.blocked + g.gaps:
                sc.point_cloud(pts.tolist(), [[0.6, 0.1, 0.7]] * len(pts), point_size=0.014)
            for tip, tail in g.torches:
                sc.line(tip.tolist(), tail.tolist()).material("#ef6c00")
        view = geometry.np.array([0.9, -0.9, 0.8])
        eye = centre + 1.7 * radius * view / geometry.np.linalg.norm(view)
        sc.move_camera(*eye, *centre, duration=0)
        sc.props("data-testid=scene3d")
        if g.missing:
            ui.label(f"Not in this job: {', '.join(g.missing)}").classes("text-grey-8")

    def _polyline(sc, pts, colour: str, most: int = 60):
        idx = geometry.np.unique(geometry.np.linspace(0, len(pts) - 1, min(most, len(pts))).round().astype(int))
        for a, b in zip(idx[:-1], idx[1:]):
            sc.line(pts[a].tolist(), pts[b].tolist()).material(colour)
