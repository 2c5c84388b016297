"""The job API's messages: what a request may say, the error code every bad one gets, and docs/API.md
generated from the models (so the document cannot drift)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from pydantic import ValidationError

from cellctl.config import CellConfig, ServiceConfig
from cellctl.service import api, apidoc
from cellctl.service.api import (ERROR_CODES, MAX_PAYLOAD_BYTES, ApiError, CancelRequest, ErrorReply, JobEvent, Keys,
                                 ListJobsRequest, ScanDrawingRequest, parse_payload)

ROOT = Path(__file__).resolve().parents[1]


def _code(raw: bytes, model=ScanDrawingRequest, required=True) -> str:
    with pytest.raises(ApiError) as e:
        parse_payload(raw, model, required=required)
    assert e.value.message and e.value.code in ERROR_CODES
    return e.value.code


def test_minimal_request_gets_the_defaults():
    r = parse_payload(b'{"scene": "smooth_cylinder"}', ScanDrawingRequest)
    assert (r.schema_version, r.kind, r.planner, r.max_steps, r.seed, r.noise, r.dry_run_cut) == \
        (1, "scan_drawing", "gnbv", None, None, True, False)
    full = {"schema_version": 1, "kind": "scan_drawing", "scene": "configs/scenes/example_plate.yaml",
            "planner": "global", "max_steps": 200, "seed": 7, "noise": False, "dry_run_cut": True,
            "requested_by": "tablet-2", "request_id": "tablet-2:0001"}
    assert parse_payload(json.dumps(full).encode(), ScanDrawingRequest).model_dump() == full


@pytest.mark.parametrize("raw, code", [
    (b"", "bad_json"),
    (b"{not json", "bad_json"),
    (b'{"scene": "smooth_cylinder"', "bad_json"),
    (b'\xff\xfe{"scene": "x"}', "bad_json"),                          # not UTF-8
    (b'{"scene": "smooth_cylinder", "max_steps": NaN}', "bad_json"),
    (b"[" * 100_000 + b"]" * 100_000, "payload_too_large"),
    (b"[" * 30_000 + b"]" * 30_000, "bad_json"),                       # deep nesting, under the size limit
    (b'["smooth_cylinder"]', "invalid_request"),
    (b'"smooth_cylinder"', "invalid_request"),
    (b"{}", "invalid_request"),                                        # scene missing
    (b'{"scene": "smooth_cylinder", "planner": "astar"}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "max_steps": "5"}', "invalid_request"),   # strict: no str -> int
    (b'{"scene": "smooth_cylinder", "max_steps": 5.5}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "noise": "yes"}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "noise": 1}', "invalid_request"),
    (b'{"scene": 5}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "speed": 2}', "invalid_request"),          # unknown field
    (b'{"scene": "smooth_cylinder", "max_steps": 0}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "max_steps": 201}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "seed": -1}', "invalid_request"),
    (b'{"scene": "../etc/passwd"}', "invalid_request"),                        # neither a name nor a .yaml
    (b'{"scene": "a\\nb.yaml"}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "kind": "cut"}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "schema_version": 2}', "unsupported_schema_version"),
    (b'{"scene": "smooth_cylinder", "schema_version": "1"}', "unsupported_schema_version"),
    (b'{"scene": "smooth_cylinder", "schema_version": true}', "unsupported_schema_version"),
])
def test_every_bad_request_has_a_code(raw, code):
    assert _code(raw) == code


def test_oversize_is_refused_before_parsing():
    raw = json.dumps({"scene": "smooth_cylinder", "requested_by": "x" * MAX_PAYLOAD_BYTES}).encode()
    assert _code(raw) == "payload_too_large"


def test_invalid_request_names_the_fields():
    with pytest.raises(ApiError) as e:
        parse_payload(b'{"planner": "astar", "extra": 1}', ScanDrawingRequest)
    locs = {d.loc for d in e.value.details}
    assert {"scene", "planner", "extra"} <= locs, locs
    reply = ErrorReply.model_validate_json(api.dumps(e.value.reply()))
    assert reply.code == "invalid_request" and "planner" in reply.message


def test_optional_payloads_default_when_absent():
    assert parse_payload(None, ListJobsRequest, required=False).limit == 20
    assert parse_payload(b"", CancelRequest, required=False).reason is None
    assert _code(b'{"limit": 1000}', ListJobsRequest, required=False) == "invalid_request"
    assert _code(b'{"state": "sleeping"}', ListJobsRequest, required=False) == "invalid_request"


def test_error_codes_are_a_closed_set():
    assert set(ERROR_CODES) == set(api.ErrorCode.__args__)
    with pytest.raises(ValidationError):
        ErrorReply(code="oops", message="x")


def test_every_registered_planner_builds_and_is_a_request_the_api_takes():
    """planners.registry is the one list: each name imports to a planner class, the API's request
    takes it, and a name not in it is refused by both."""
    from planners.registry import PLANNERS, make_planner, planner_class

    for name in PLANNERS:
        assert callable(planner_class(name).next_view)
        assert ScanDrawingRequest(scene="t_piece", planner=name).planner == name
    assert ScanDrawingRequest(scene="t_piece").planner == "gnbv"
    with pytest.raises(ValidationError):
        ScanDrawingRequest(scene="t_piece", planner="nope")
    with pytest.raises(ValueError, match="unknown planner 'nope'"):
        make_planner("nope", None)


def test_examples_round_trip_and_events_reject_bad_phases():
    for name, msg in apidoc.examples().items():
        again = type(msg).model_validate_json(msg.model_dump_json())
        assert again == msg, name
    ev = apidoc.examples()["event_step"].model_dump()
    with pytest.raises(ValidationError):
        JobEvent.model_validate({**ev, "phase": "sleeping"})
    with pytest.raises(ValidationError):
        JobEvent.model_validate({**ev, "seq": -1})


def test_keys():
    k = Keys("sim-1")
    assert (k.submit, k.jobs, k.status, k.alive) == ("cell/sim-1/jobs/submit", "cell/sim-1/jobs", "cell/sim-1/status",
                                                     "cell/sim-1/alive")
    assert k.cancel("J") == "cell/sim-1/jobs/J/cancel" and k.events("J") == "cell/sim-1/jobs/J/events"


def test_api_doc_is_generated_from_the_models():
    committed = (ROOT / "docs" / "API.md").read_text()
    assert committed == apidoc.render(), "docs/API.md is stale: run `python -m cellctl.service.apidoc > docs/API.md`"
    for key in ("jobs/submit", "jobs/<job_id>/cancel", "jobs/<job_id>/events", "/status", "/alive"):
        assert key in committed
    assert "no reply within" in committed and "access control" in committed
    for code in ERROR_CODES:
        assert f"`{code}`" in committed


def test_service_config_is_validated():
    assert ServiceConfig().zenoh_mode == "peer"
    with pytest.raises(ValidationError, match="router"):
        ServiceConfig(zenoh_mode="client")
    with pytest.raises(ValidationError):
        ServiceConfig(listen=["127.0.0.1:7447"])  # no protocol
    with pytest.raises(ValidationError):
        ServiceConfig(queue_max=0)
    with pytest.raises(ValidationError):
        ServiceConfig(job_timeout_s=-1)
    with pytest.raises(ValidationError):
        ServiceConfig(data_dir="x", unknown=1)
    assert CellConfig(service={"zenoh_mode": "client", "connect": ["tcp/10.0.0.2:7447"]}).service.connect


def test_the_sim_config_has_a_service_section():
    from cellctl.config import load_cell_config

    cfg, _ = load_cell_config(None)
    assert cfg.service.listen and cfg.service.queue_max >= 1 and cfg.service.job_timeout_s > 0


@pytest.mark.parametrize("raw, what", [
    (b'{"scene": "../../etc/passwd.yaml", "scene": "t_piece"}', "given twice"),
    (b'{"scene": "t_piece", "scene": "t_piece"}', "given twice"),
    (b'{"scene": "t_piece", "requested_by": "\\ud800"}', "surrogate"),
    (b'{"scene": "t_piece", "x\\udfff": 1}', "surrogate"),
    (b'{"scene": ' + b"[" * 40 + b"]" * 40 + b"}", "nested deeper"),
    (b'{"scene": ' + b"[" * 5000 + b"]" * 5000 + b"}", "recursion"),
])
def test_json_that_could_mean_two_things_is_bad_json(raw, what):
    """One code per class of malformed input, decided before any model sees it: a duplicate key (the
    last would win in one parser, the first in another), a lone surrogate, nesting past MAX_JSON_DEPTH."""
    with pytest.raises(ApiError) as e:
        parse_payload(raw, ScanDrawingRequest)
    assert e.value.code == "bad_json" and what in e.value.message, e.value.message
