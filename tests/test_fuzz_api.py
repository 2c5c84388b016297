"""Bad input, generated: property-based fuzzing (hypothesis) of every request model in process, and of every
queryable of a real `cellctl serve` over raw Zenoh. Every malformed payload must get an error reply with a
stable code (never internal_error, never a crash), the service must stay up and its job store unchanged;
and every field a request can set must be bounded (docs/RELIABILITY.md has the counts).

Each generated case is a *valid* request with one or more defects that make it invalid by construction
(wrong type, out of range, too long, bad pattern, unknown or missing field, NaN/Infinity, huge or deeply
nested values, invalid UTF-8, truncated or trailing bytes, oversized), so its expected error code is known
without asking the code under test. Runs are reproducible (derandomize, no example database). No fuzzed
submit can start a scan: every submit payload is checked locally to be refused before it is sent."""

from __future__ import annotations

import functools
import inspect
import json
import re
import sqlite3
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel, Field

from cellctl.config import ServiceConfig, load_cell_config
from cellctl.service import api
from cellctl.service.api import (CHUNK_MAX, ERROR_CODES, MAX_JSON_DEPTH, MAX_MESSAGE_BYTES, MAX_PAYLOAD_BYTES,
                                 PLANNER_NAMES, REQUEST_ID_PATTERN, ApiError, ApiModel, CancelRequest, FileChunkRequest, CellStatus, ErrorReply, JobRecord, ListJobsRequest, ScanDrawingRequest,
                                 parse_payload)
from cellctl.service.api import CommissionPaintRequest
from cellctl.service.loopback import ServiceProcess
from cellctl.service.server import CellService
from cellctl.service.store import JobStore
from sim.scenes.catalog import SCENE_NAMES

EXAMPLES = 1000  # distinct generated payloads per model and per endpoint, at least (the figure)
# 1,300 tries give over 1,000 distinct payloads (hypothesis repeats some simple ones); fixed seed, no database
FUZZ = settings(max_examples=1300, deadline=None, derandomize=True, database=None, print_blob=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.filter_too_much, HealthCheck.large_base_example])
OVERSIZE_MAX = MAX_MESSAGE_BYTES - 32 * 1024  # oversized, yet under the transport cap: the service must answer
REQUEST_MODELS = (ScanDrawingRequest, ListJobsRequest, CancelRequest, FileChunkRequest, CommissionPaintRequest)


# --- generated JSON, with the tokens json.dumps cannot write ------------------------------------------------
@dataclass(frozen=True)
class Raw:
    """JSON text emitted verbatim: NaN/Infinity tokens, huge number literals, deep nesting."""

    text: str
    jtype: str                 # its JSON type once parsed
    always_bad: bool = False   # bad_json wherever it stands (NaN, Infinity, nested past MAX_JSON_DEPTH)
    maybe_bad: bool = False    # json.loads may refuse it (recursion depth, over 4300 digits)


def jtype(v) -> str:
    if isinstance(v, Raw):
        return v.jtype
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "boolean"
    return {int: "integer", float: "number", str: "string", list: "array", dict: "object"}[type(v)]


def encode(v, seps: tuple[str, str] = (",", ":")) -> str:
    if isinstance(v, Raw):
        return v.text
    if isinstance(v, dict):
        return "{" + seps[0].join(json.dumps(k, ensure_ascii=False) + seps[1] + encode(x, seps)
                                  for k, x in v.items()) + "}"
    if isinstance(v, list):
        return "[" + seps[0].join(encode(x, seps) for x in v) + "]"
    return json.dumps(v, ensure_ascii=False)


SEPARATORS = st.sampled_from([(",", ":"), (", ", ": "), ("\n,\t", " :\r\n")])
NUMERIC_STRINGS = st.sampled_from(["NaN", "nan", "Infinity", "-Infinity", "inf", "1e400", "5", " 5", "0x10", "1_000",
                                   "", "null", "true"])
HUGE_INTS = st.one_of(st.sampled_from([2**63, 2**63 + 1, 2**64, -(2**63) - 1, 10**30, -(10**30)]),
                      st.integers(min_value=2**63, max_value=2**256),
                      st.integers(min_value=-(2**256), max_value=-(2**63)))
SCALARS = st.one_of(st.none(), st.booleans(), st.integers(min_value=-(2**70), max_value=2**70), HUGE_INTS,
                    st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=40), NUMERIC_STRINGS)
PLAIN = st.recursive(SCALARS, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
                     max_leaves=8)
NAN_TOKENS = st.sampled_from([Raw(t, "number", always_bad=True) for t in ("NaN", "Infinity", "-Infinity")])
OVERFLOW_FLOATS = st.sampled_from([Raw(t, "number") for t in ("1e400", "-1e400", "1E+999", "-0.0", "5.0", "1.5e2")])
HUGE_LITERALS = st.integers(min_value=19, max_value=5000).map(
    lambda k: Raw("9" * k, "integer", maybe_bad=k > 4000))  # Python refuses int literals over 4300 digits
# nested past MAX_JSON_DEPTH is bad_json, however deep (as a field's value one level more: either code at the edge)
DEEP = st.tuples(st.integers(min_value=1, max_value=3000), st.booleans()).map(lambda t: (
    Raw("[" * t[0] + "]" * t[0], "array", always_bad=t[0] > MAX_JSON_DEPTH, maybe_bad=t[0] == MAX_JSON_DEPTH) if t[1]
    else Raw('{"a":' * t[0] + "null" + "}" * t[0], "object", always_bad=t[0] > MAX_JSON_DEPTH,
             maybe_bad=t[0] == MAX_JSON_DEPTH)))
LONG_TEXT = st.tuples(st.text(min_size=1, max_size=4), st.integers(100, 20_000)).map(lambda t: (t[0] * t[1])[:t[1]])
ANY_VALUE = st.one_of(PLAIN, NAN_TOKENS, OVERFLOW_FLOATS, HUGE_LITERALS, DEEP, LONG_TEXT)
BAD_UTF8 = st.sampled_from([b"\xff", b"\xfe", b"\x80", b"\xc0\xaf", b"\xed\xa0\x80", b"\xf5\x80\x80\x80", b"\xc3",
                            b"\xe2\x82", b"\xf0\x9f\x98"])
CONTROL = st.sampled_from([chr(c) for c in (*range(0x20), 0x7F)])


# --- the request models: valid bases, field specs from the JSON schema ---------------------------------------
def field_specs(model: type[BaseModel]) -> dict[str, dict]:
    """name -> {types, required, minimum, maximum, maxLength, pattern, enum, const}, from the JSON schema (so a
    new field is fuzzed without touching this file)."""
    schema = model.model_json_schema()
    out = {}
    for name, prop in schema["properties"].items():
        alts = prop.get("anyOf", [prop])
        types = {a.get("type", "object" if "$ref" in a else None) for a in alts}
        if "number" in types:  # a float field takes 5 too
            types.add("integer")
        spec: dict = {"types": types, "required": name in schema.get("required", [])}
        for a in alts:
            spec.update({k: a[k] for k in ("minimum", "maximum", "maxLength", "pattern", "enum", "const") if k in a})
        out[name] = spec
    return out


REQUESTED_BY = st.text(alphabet="abcXYZ019 .@-_", min_size=1, max_size=64)
VALID = {
    ScanDrawingRequest: st.fixed_dictionaries(
        {"scene": st.sampled_from(SCENE_NAMES)},
        optional={"schema_version": st.just(1), "kind": st.just("scan_drawing"),
                  "planner": st.sampled_from(PLANNER_NAMES),
                  "max_steps": st.none() | st.integers(1, 200), "seed": st.none() | st.integers(0, 2**31 - 1),
                  "noise": st.booleans(), "dry_run_cut": st.booleans(), "requested_by": st.none() | REQUESTED_BY,
                  "request_id": st.none() | st.from_regex(REQUEST_ID_PATTERN, fullmatch=True)}),
    ListJobsRequest: st.fixed_dictionaries(
        {}, optional={"schema_version": st.just(1), "limit": st.integers(1, 200),
                      "state": st.none() | st.sampled_from(["queued", "running", "done", "failed", "cancelled"])}),
    CancelRequest: st.fixed_dictionaries(
        {}, optional={"schema_version": st.just(1), "reason": st.none() | st.text(max_size=200)}),
    FileChunkRequest: st.fixed_dictionaries(
        {}, optional={"schema_version": st.just(1), "offset": st.integers(0, 2**40), "length": st.integers(1, CHUNK_MAX)}),
    CommissionPaintRequest: st.fixed_dictionaries(
        {"name": st.text(alphabet="abcXYZ019 -_", min_size=1, max_size=40)},
        optional={"schema_version": st.just(1), "requested_by": st.none() | REQUESTED_BY,
                  "twin_finish": st.none() | st.sampled_from(["rust_red", "galvanized"]),
                  "twin_paint": st.none() | st.sampled_from(["pink", "white"]),
                  "twin_light": st.none() | st.sampled_from(["dim", "normal"]), "twin_no_paint": st.booleans()}),
}
REQUIRED = {ScanDrawingRequest: True, ListJobsRequest: False, CancelRequest: False, FileChunkRequest: False,
            CommissionPaintRequest: True}


@dataclass
class Case:
    """A malformed payload and the error codes it may get (one, except where json.loads' own limits decide
    between bad_json and the next check)."""

    raw: bytes
    codes: frozenset[str]
    label: str
    fields: tuple[str, ...] = ()  # fields whose defect pydantic must name in the details


def _field_defects(spec: dict) -> list[tuple[str, st.SearchStrategy]]:
    """(label, strategy of a value that this field refuses)."""
    types = spec["types"]
    out = [("wrong_type", ANY_VALUE.filter(lambda v: jtype(v) not in types)), ("nan_token", NAN_TOKENS)]
    if "const" in spec:
        c = spec["const"]
        if isinstance(c, int):  # strict: 1.0, "1" and true are not 1
            bad = st.one_of(st.integers(-3, 1000).filter(lambda v: v != c), st.sampled_from([str(c), float(c), True]))
        else:
            bad = st.sampled_from([c.upper(), c + " ", "", c[:-1]])
        out.append(("bad_const", bad))
    if "minimum" in spec or "maximum" in spec:
        lo, hi = spec.get("minimum"), spec.get("maximum")
        parts = []
        if hi is not None:
            parts += [st.integers(hi + 1, hi + 1000), st.integers(min_value=hi + 1), HUGE_INTS.filter(lambda v: v > hi),
                      HUGE_LITERALS.filter(lambda r: len(r.text) > len(str(hi)))]
        if lo is not None:
            parts += [st.integers(lo - 1000, lo - 1), st.integers(max_value=lo - 1), HUGE_INTS.filter(lambda v: v < lo)]
        out.append(("out_of_range", st.one_of(parts)))
    if "maxLength" in spec:
        n = spec["maxLength"]
        out.append(("too_long", st.integers(n + 1, n + 5000).map(lambda k: "x" * k)))
    if "pattern" in spec:
        pat = spec["pattern"]
        out.append(("bad_pattern", st.one_of(
            st.just(""),
            st.tuples(st.text(alphabet="abcxyz_0123.yaml/", max_size=30), CONTROL, st.integers(0, 30)).map(
                lambda t: t[0][:t[2]] + t[1] + t[0][t[2]:]),
            st.text(alphabet="ABC/\\<>#*?\"'$%&+=:;,!|~^`", min_size=1, max_size=20)).filter(
                lambda s: not re.search(pat, s))))
    if "enum" in spec:
        enum = spec["enum"]
        near = [v for e in enum for v in (e.upper(), " " + e, e + "\x00", e[:-1], e + "s") if v not in enum]
        out.append(("not_in_enum", st.one_of(st.text(max_size=20).filter(lambda s: s not in enum),
                                             st.sampled_from(near))))
    return out


@functools.cache
def _mutation(model: type[BaseModel]) -> st.SearchStrategy[tuple[str, str, object]]:
    """(label, field, refused value | MISSING) for one field of the model, or an unknown field."""
    specs = field_specs(model)
    options: dict[str, list] = {}
    for name, spec in specs.items():
        for label, values in _field_defects(spec):
            options.setdefault(label, []).append(values.map(lambda v, n=name, lb=label: (lb, n, v)))
        if spec["required"]:
            options.setdefault("missing", []).append(st.just(("missing", name, MISSING)))
    near_miss = st.sampled_from([v for n in sorted(specs) for v in
                                 (n.upper(), n + " ", " " + n, n.replace("_", "-"), n + "\x00", n[:-1])])
    unknown_key = st.one_of(st.text(max_size=30), near_miss, st.just("__proto__"), st.just("$ref")).filter(
        lambda k: k not in specs)
    options["unknown_field"] = [st.tuples(unknown_key, ANY_VALUE).map(lambda t: ("unknown_field", t[0], t[1]))]
    # the kind of defect first, then the field: every kind gets its share whatever the number of fields (the
    # first kind is drawn most: hypothesis favours simple choices, so the one with the largest space goes first)
    kinds = sorted(options, key=lambda k: (KIND_ORDER.index(k) if k in KIND_ORDER else len(KIND_ORDER), k))
    per_kind = {k: st.one_of(options[k]) for k in kinds}
    return st.sampled_from(kinds).flatmap(per_kind.__getitem__)


KIND_ORDER = ["wrong_type", "unknown_field", "out_of_range", "too_long", "bad_pattern", "not_in_enum", "nan_token",
              "bad_const", "missing"]


MISSING = object()


def _codes_for(mutations, base_code: str = "invalid_request") -> frozenset[str]:
    values = [v for _, _, v in mutations]
    if any(isinstance(v, Raw) and v.always_bad for v in values):
        return frozenset({"bad_json"})
    version = any(f == "schema_version" and lb != "unknown_field" for lb, f, _ in mutations)
    codes = {"unsupported_schema_version" if version else base_code}
    if any(isinstance(v, Raw) and v.maybe_bad for v in values):
        codes.add("bad_json")
    return frozenset(codes)


@st.composite
def field_case(draw, model: type[BaseModel]) -> Case:
    """A valid request with 1-3 refused values on distinct fields (so no defect undoes another)."""
    obj = dict(draw(VALID[model]))
    muts = draw(st.lists(_mutation(model), min_size=1, max_size=3, unique_by=lambda m: m[1]))
    for label, name, value in muts:
        if value is MISSING:
            obj.pop(name, None)
        else:
            obj[name] = value
    if draw(st.booleans()):  # order of keys must not matter
        obj = dict(reversed(list(obj.items())))
    raw = encode(obj, draw(SEPARATORS)).encode()
    label = muts[0][0] if len(muts) == 1 else "several_fields"
    return _sized(Case(raw, _codes_for(muts), label, _named(muts)))


def _named(muts) -> tuple[str, ...]:
    """The fields an invalid_request reply must name."""
    return tuple(f for lb, f, _ in muts if lb != "unknown_field" and f != "schema_version")


def _sized(case: Case) -> Case:
    """Long values can add up past the size limit, which is checked first."""
    if len(case.raw) > MAX_PAYLOAD_BYTES:
        return Case(case.raw, frozenset({"payload_too_large"}), case.label)
    return case


@st.composite
def duplicate_key_case(draw, model: type[BaseModel]) -> Case:
    """A key given twice is refused as bad_json, whatever the two values (which one would count is not
    defined by JSON: a request must not mean one thing to the cell and another to a proxy)."""
    obj = draw(VALID[model].filter(bool))
    name = draw(st.sampled_from(sorted(obj)))
    value = draw(st.one_of(st.just(obj[name]), PLAIN))
    text = encode(obj)
    text = text[:-1] + "," + json.dumps(name) + ":" + encode(value) + "}"
    return _sized(Case(text.encode(), frozenset({"bad_json"}), "duplicate_key"))


@st.composite
def byte_case(draw, model: type[BaseModel]) -> Case:
    """Byte-level damage to a valid request."""
    raw = encode(draw(VALID[model]), draw(SEPARATORS)).encode()
    kind = draw(st.sampled_from(["invalid_utf8", "truncated", "trailing_garbage", "bom", "whitespace_only",
                                 "latin1", "nul_byte"]))
    if kind == "invalid_utf8":
        i = draw(st.integers(0, len(raw)))
        raw = raw[:i] + draw(BAD_UTF8) + raw[i:]
    elif kind == "truncated":
        raw = raw[:draw(st.integers(1, len(raw) - 1))]
    elif kind == "trailing_garbage":
        raw += draw(st.sampled_from([b"x", b"}", b",{}", b"{}", b"]", b"0", b"\x00", b"//", b"null"]))
    elif kind == "bom":
        raw = b"\xef\xbb\xbf" + raw
    elif kind == "whitespace_only":
        raw = draw(st.text(alphabet=" \t\r\n", min_size=1, max_size=50)).encode()
    elif kind == "latin1":  # a non-ASCII text sent in the wrong encoding
        text = draw(st.text(alphabet="éàüßñ", min_size=1, max_size=5))  # all lead bytes in Latin-1
        raw = raw[:-1] + b',"x":"' + text.encode("latin-1") + b'"}'
    else:
        i = draw(st.integers(0, len(raw)))
        raw = raw[:i] + b"\x00" + raw[i:]
    if kind in ("invalid_utf8", "latin1"):
        _assert_not_utf8(raw)
    return Case(raw, frozenset({"bad_json"}), kind)


def _assert_not_utf8(raw: bytes) -> None:
    with pytest.raises(UnicodeDecodeError):
        raw.decode("utf-8")


@st.composite
def not_object_case(draw) -> Case:
    v = draw(st.one_of(SCALARS, st.lists(PLAIN, max_size=5), NAN_TOKENS, OVERFLOW_FLOATS, HUGE_LITERALS,
                       DEEP.filter(lambda r: r.jtype == "array")))
    codes = {"bad_json"} if isinstance(v, Raw) and v.always_bad else {"invalid_request"}
    if isinstance(v, Raw) and v.maybe_bad:
        codes.add("bad_json")
    return Case(encode(v).encode(), frozenset(codes), "not_an_object")


@st.composite
def oversize_case(draw, model: type[BaseModel]) -> Case:
    """Over MAX_PAYLOAD_BYTES (refused before parsing, whatever the bytes), under the transport cap."""
    size = draw(st.one_of(st.just(MAX_PAYLOAD_BYTES + 1), st.integers(MAX_PAYLOAD_BYTES + 1, OVERSIZE_MAX)))
    head = encode(draw(VALID[model])).encode()
    how = draw(st.sampled_from(["spaces", "long_string", "big_array", "junk"]))
    if how == "spaces":  # otherwise a valid request
        raw = head + b" " * (size - len(head))
    elif how == "long_string":
        raw = head[:-1] + (b"," if len(head) > 2 else b"") + b'"pad":"' + b"a" * size + b'"}'
    elif how == "big_array":
        raw = b"[" + b"0," * (size // 2) + b"0]"
    else:
        junk = draw(st.binary(min_size=1, max_size=64))
        raw = (junk * (size // len(junk) + 1))[:size]
    return Case(raw, frozenset({"payload_too_large"}), "oversized")


@st.composite
def junk_case(draw) -> Case:
    """Random bytes that are not UTF-8."""
    b = draw(st.binary(max_size=300))
    i = draw(st.integers(0, len(b)))
    raw = b[:i] + draw(st.sampled_from([b"\xff", b"\xfe"])) + b[i:]  # never in UTF-8, whatever surrounds them
    return Case(raw, frozenset({"bad_json"}), "binary_junk")


@functools.cache
def malformed(model: type[BaseModel]) -> st.SearchStrategy[Case]:
    cases = [field_case(model)] * 4 + [duplicate_key_case(model), byte_case(model), byte_case(model),
                                       not_object_case(), oversize_case(model), junk_case()]
    if REQUIRED[model]:
        cases.append(st.just(Case(b"", frozenset({"bad_json"}), "empty")))
    return st.sampled_from(cases).flatmap(lambda c: c)


def check_error(code: str, message: str, details: list, case: Case) -> None:
    assert code in case.codes and code in ERROR_CODES, (case.label, code, message, case.raw[:300])
    assert message, case.label
    if code == "invalid_request" and case.fields:
        locs = {d.loc.split(".")[0] for d in details}
        assert locs & set(case.fields), (case.label, case.fields, locs, message)


# --- model level: parse_payload, in process ------------------------------------------------------------------
@pytest.mark.parametrize("model", REQUEST_MODELS, ids=lambda m: m.__name__)
def test_valid_bases_are_valid(model):
    """The generators' premise: a case is a valid request plus its defects."""
    # too_slow is a wall-clock check of the data generation: it would depend on the machine's load
    @settings(max_examples=100, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow])
    @given(VALID[model])
    def run(obj):
        assert isinstance(parse_payload(encode(obj).encode(), model, required=REQUIRED[model]), model)

    run()


@pytest.mark.parametrize("model", REQUEST_MODELS, ids=lambda m: m.__name__)
def test_every_malformed_payload_gets_a_coded_error(model):
    seen: Counter[str] = Counter()
    distinct: set[bytes] = set()

    @FUZZ
    @given(malformed(model))
    def run(case: Case):
        try:
            parsed = parse_payload(case.raw, model, required=REQUIRED[model])
        except ApiError as e:
            check_error(e.code, e.message, e.details, case)
            reply = ErrorReply.model_validate_json(api.dumps(e.reply()))  # what the service sends
            assert reply.code == e.code and len(reply.details) <= 20
        else:
            pytest.fail(f"{case.label}: {case.raw[:300]!r} was accepted as {parsed!r}")
        seen[case.label] += 1
        distinct.add(case.raw)

    run()
    print(f"\n{model.__name__}: {sum(seen.values())} payloads ({len(distinct)} distinct): {dict(seen)}")
    assert len(distinct) >= EXAMPLES
    assert {"wrong_type", "out_of_range" if model not in (CancelRequest, CommissionPaintRequest) else "too_long", "unknown_field",
            "invalid_utf8", "oversized", "not_an_object", "several_fields", "duplicate_key"} <= set(seen), seen


# --- bounds --------------------------------------------------------------------------------------------------
def unbounded(schema: dict, root: dict | None = None, path: str = "") -> list[str]:
    """Paths of the values in a JSON schema that have no explicit bound: a number without minimum and
    maximum, a string without maxLength (or enum/const), a list without maxItems, an open object."""
    root = root or schema
    if "$ref" in schema:
        return unbounded(root["$defs"][schema["$ref"].split("/")[-1]], root, path)
    if "anyOf" in schema:
        return [p for alt in schema["anyOf"] for p in unbounded(alt, root, path)]
    if "const" in schema or "enum" in schema:
        return []
    t = schema.get("type")
    if t in ("integer", "number"):
        lo = "minimum" in schema or "exclusiveMinimum" in schema
        hi = "maximum" in schema or "exclusiveMaximum" in schema
        return [] if lo and hi else [f"{path}: {t} without {'minimum' if not lo else 'maximum'}"]
    if t == "string":
        return [] if "maxLength" in schema else [f"{path}: string without maxLength"]
    if t == "array":
        own = [] if "maxItems" in schema else [f"{path}: array without maxItems"]
        return own + unbounded(schema.get("items", {}), root, path + "[]")
    if t == "object":
        own = [] if schema.get("additionalProperties") is False else [f"{path}: object open to any key"]
        return own + [p for k, s in schema.get("properties", {}).items()
                      for p in unbounded(s, root, f"{path}.{k}" if path else k)]
    if t in ("boolean", "null"):
        return []
    return [f"{path}: no type (any value)"]


def test_the_fuzzed_models_are_every_request_the_service_parses():
    parsed = set(re.findall(r"parse_payload\(payload, (\w+)", inspect.getsource(CellService)))
    requests = {m.__name__ for m in ApiModel.__subclasses__() if m.__name__.endswith("Request")}
    assert parsed == requests == {m.__name__ for m in REQUEST_MODELS}


@pytest.mark.parametrize("model", REQUEST_MODELS, ids=lambda m: m.__name__)
def test_every_request_field_is_bounded(model):
    assert unbounded(model.model_json_schema()) == []


def test_the_bound_check_catches_an_unbounded_field():
    class Loose(ApiModel):
        n: int = Field(ge=0)
        x: float = Field(le=1)
        s: str
        tags: list[str] = Field(max_length=3)
        free: list[int]
        ok: int = Field(0, ge=0, le=5)

    assert sorted(unbounded(Loose.model_json_schema())) == [
        "free: array without maxItems", "free[]: integer without minimum", "n: integer without maximum",
        "s: string without maxLength", "tags[]: string without maxLength", "x: number without minimum"]


def test_what_a_request_can_make_big_or_long_is_bounded():
    """Every job has a timeout; the numbers behind memory and time (steps, grid, search radius, queue) are
    capped in the config models, and a request can only lower the step limit."""
    from planners.config import GridConfig, NBVConfig, PlannersConfig

    cfg, _ = load_cell_config()
    assert 0 < cfg.service.job_timeout_s <= 86400 and 1 <= cfg.service.queue_max <= 1000
    assert [p for p in unbounded(ServiceConfig.model_json_schema()) if "integer" in p or "number" in p] == []
    schema = ServiceConfig.model_json_schema()["properties"]["job_timeout_s"]
    assert schema["exclusiveMinimum"] == 0 and schema["maximum"] <= 86400
    step_cap = PlannersConfig.model_json_schema()["properties"]["max_steps"]["maximum"]
    assert ScanDrawingRequest.model_json_schema()["properties"]["max_steps"]["anyOf"][0]["maximum"] == step_cap
    assert NBVConfig.model_json_schema()["properties"]["search_radius_m"]["maximum"] <= 1.5
    with pytest.raises(ValueError, match="cells"):
        GridConfig(voxel_m=0.002, lo_m=(-1, -1, 0), hi_m=(1, 1, 1))  # 500 M cells
    assert MAX_PAYLOAD_BYTES <= 64 * 1024 and MAX_MESSAGE_BYTES <= 1024 * 1024


# --- wire level: a real service, raw Zenoh queries -----------------------------------------------------------
SEEDED = {"20250101T000000Z-00000a": "done", "20250101T000001Z-00000b": "cancelled",
          "20250101T000002Z-00000c": "failed", "20250101T000003Z-00000d": "interrupted"}
PATHS = {"done": ["running", "done"], "cancelled": ["cancelled"], "failed": ["running", "failed"],
         "interrupted": ["running", "interrupted"]}


def _seed_store(path: Path) -> None:
    """Ended jobs, written before the service starts: nothing to run, yet records to read and refuse to cancel."""
    store = JobStore(path)
    try:
        req = ScanDrawingRequest(scene="smooth_cylinder", max_steps=2, noise=False, requested_by="fuzz")
        for job_id, final in SEEDED.items():
            store.create(job_id, "sim-1", req, f"/nonexistent/{job_id}", at="2025-01-01T00:00:00.000Z")
            for state in PATHS[final]:
                store.transition(job_id, state, "seeded", error="seeded failure" if state == "failed" else None)
    finally:
        store.close()


@dataclass
class Cell:
    svc: ServiceProcess
    session: zenoh.Session
    root: str

    def query(self, key: str, raw: bytes) -> list:
        return list(self.session.get(key, payload=raw, timeout=10.0))

    def store_rows(self):
        """The whole job store, read-only: jobs and transitions, every column."""
        con = sqlite3.connect(f"file:{self.svc.data_dir / 'jobs.sqlite'}?mode=ro", uri=True)
        try:
            return (con.execute("SELECT * FROM jobs ORDER BY id").fetchall(),
                    con.execute("SELECT * FROM transitions ORDER BY job_id, n").fetchall())
        finally:
            con.close()


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """One service for the module; job_timeout_s small in case a scan ever started (none may)."""
    svc = ServiceProcess(tmp_path_factory.mktemp("fuzzcell"), queue_max=1, job_timeout_s=10.0)
    _seed_store(svc.data_dir / "jobs.sqlite")
    svc.start()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([svc.endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")  # big payloads go over TCP, as from a tablet
    session = zenoh.open(conf)
    c = Cell(svc, session, f"cell/{svc.cell_id}")
    before = c.store_rows()
    assert [r[1] for r in before[0]] == list(SEEDED) and [r[4] for r in before[0]] == list(SEEDED.values())
    try:
        yield c
        assert svc.proc.poll() is None, "the service died"
        assert c.store_rows() == before, "the job store changed"
        with svc.client() as client:
            st_ = client.status()
            assert st_.jobs_total == len(SEEDED) and st_.accepting_jobs and st_.running_job is None
            assert {j.job_id: j.state for j in client.jobs(limit=200).jobs} == SEEDED
            assert client.alive()
    finally:
        session.close()
        rc, _ = svc.stop()
        svc.kill()
    log = svc.log.read_text()
    assert rc == 0 and "Traceback" not in log, log[-3000:]  # no internal_error: log.exception writes one


def _would_be_accepted(raw: bytes) -> bool:
    """What the service would queue: parses and names a scene that exists."""
    try:
        req = parse_payload(raw, ScanDrawingRequest)
    except ApiError:
        return False
    return req.scene in SCENE_NAMES or Path(req.scene).is_file()


def _one_error(replies: list, case: Case) -> str:
    assert len(replies) == 1, (case.label, len(replies))
    r = replies[0]
    assert r.err is not None, (case.label, r.ok.payload.to_bytes()[:300], case.raw[:300])
    err = ErrorReply.model_validate_json(r.err.payload.to_bytes())
    check_error(err.code, err.message, err.details, case)
    return err.code


def _fuzz_endpoint(cell: Cell, strategy, send, must_see: set[str]) -> Counter:
    seen: Counter[str] = Counter()
    distinct: set = set()
    before = cell.store_rows()

    @FUZZ
    @given(strategy)
    def run(arg):
        label, key = send(arg)
        seen[label] += 1
        distinct.add(key)

    run()
    assert cell.store_rows() == before
    assert cell.svc.proc.poll() is None
    print(f"\n{sum(seen.values())} payloads ({len(distinct)} distinct): {dict(seen)}")
    assert len(distinct) >= EXAMPLES and must_see <= set(seen), seen
    return seen


WIRE_KINDS = {"wrong_type", "unknown_field", "several_fields", "duplicate_key", "nan_token", "not_an_object",
              "invalid_utf8", "truncated", "binary_junk", "oversized"}


UNKNOWN_SCENES = st.one_of(
    st.text(alphabet="abcdefghijklmnopqrstuvwxyz0123456789_", min_size=1, max_size=64),
    st.text(alphabet="abc/._-éü ", min_size=1, max_size=40).map(lambda s: f"/nonexistent/{s}.yaml"),
    st.sampled_from(["../etc/passwd.yaml", "/dev/null.yaml", "~/.yaml", "C:\\scene.yml"])).filter(
        lambda s: s not in SCENE_NAMES and not Path(s).is_file())


@st.composite
def submit_case(draw) -> Case:
    """Malformed submits, and well-formed ones that name no scene the cell has (refused before queueing)."""
    if draw(st.integers(0, 9)) == 0:
        obj = {**draw(VALID[ScanDrawingRequest]), "scene": draw(UNKNOWN_SCENES)}
        return Case(encode(obj).encode(), frozenset({"invalid_request"}), "unknown_scene", ("scene",))
    return draw(malformed(ScanDrawingRequest))


def test_submit_fuzz(cell):
    key = f"{cell.root}/jobs/submit"

    def send(case: Case):
        assert not _would_be_accepted(case.raw), f"the generator made a valid submit: {case.raw[:300]!r}"
        _one_error(cell.query(key, case.raw), case)
        return case.label, case.raw

    _fuzz_endpoint(cell, submit_case(), send, WIRE_KINDS | {"unknown_scene", "missing", "out_of_range", "empty"})


def test_jobs_list_fuzz(cell):
    key = f"{cell.root}/jobs"

    def send(case: Case):
        _one_error(cell.query(key, case.raw), case)
        return case.label, case.raw

    _fuzz_endpoint(cell, malformed(ListJobsRequest), send, WIRE_KINDS | {"out_of_range", "not_in_enum"})


def _key_chunk(s: str) -> bool:
    try:
        zenoh.KeyExpr(f"cell/x/jobs/{s}")
    except zenoh.ZError:
        return False
    return True


JOB_IDS = st.one_of(
    st.sampled_from(list(SEEDED)),
    st.from_regex(api.JOB_ID_PATTERN, fullmatch=True),
    st.text(alphabet="abcXYZ019-_.:+=,~!'()éß中😀", min_size=1, max_size=200)).filter(
        lambda s: s not in ("submit",) and not s.startswith("@") and _key_chunk(s))
ANY_PAYLOAD = st.one_of(
    st.binary(max_size=500),
    st.sampled_from(REQUEST_MODELS).flatmap(malformed).map(lambda c: c.raw),
    VALID[ListJobsRequest].map(lambda o: encode(o).encode()),
    st.integers(MAX_PAYLOAD_BYTES - 2, MAX_PAYLOAD_BYTES + 2).map(lambda n: b"{" * n),  # the size boundary
)


def test_job_record_fuzz(cell):
    """The payload is ignored (up to the size limit); the key's job id is fuzzed too."""
    records = {}

    def send(arg):
        job_id, raw = arg
        replies = cell.query(f"{cell.root}/jobs/{job_id}", raw)
        if len(raw) > MAX_PAYLOAD_BYTES:
            label = "oversized"
            _one_error(replies, Case(raw, frozenset({"payload_too_large"}), label))
        elif job_id in SEEDED:
            assert len(replies) == 1 and replies[0].ok is not None, job_id
            rec = JobRecord.model_validate_json(replies[0].ok.payload.to_bytes())
            assert rec.job_id == job_id and rec.state == SEEDED[job_id]
            assert records.setdefault(job_id, rec) == rec  # the same record, whatever the payload
            label = "existing_job"
        else:
            label = "unknown_job"
            _one_error(replies, Case(raw, frozenset({"not_found"}), label))
        return label, (job_id, raw)

    _fuzz_endpoint(cell, st.tuples(JOB_IDS, ANY_PAYLOAD), send, {"existing_job", "unknown_job", "oversized"})


def test_cancel_fuzz(cell):
    """Malformed cancel payloads, on ended jobs and on unknown ids: the payload is checked first."""
    def send(arg):
        job_id, case = arg
        _one_error(cell.query(f"{cell.root}/jobs/{job_id}/cancel", case.raw), case)
        return case.label, (job_id, case.raw)

    _fuzz_endpoint(cell, st.tuples(JOB_IDS, malformed(CancelRequest)), send, WIRE_KINDS | {"too_long"})


def test_status_fuzz(cell):
    """Status ignores its payload up to the size limit; over it, payload_too_large like every key."""
    def send(raw: bytes):
        replies = cell.query(f"{cell.root}/status", raw)
        if len(raw) > MAX_PAYLOAD_BYTES:
            _one_error(replies, Case(raw, frozenset({"payload_too_large"}), "oversized"))
            return "oversized", raw
        assert len(replies) == 1 and replies[0].ok is not None
        s = CellStatus.model_validate_json(replies[0].ok.payload.to_bytes())
        assert s.jobs_total == len(SEEDED) and s.queue_length == 0 and s.running_job is None
        return "ignored_payload", raw

    _fuzz_endpoint(cell, ANY_PAYLOAD, send, {"ignored_payload", "oversized"})


def test_a_query_over_the_transport_cap_is_dropped_and_the_cell_carries_on(cell):
    """Over MAX_MESSAGE_BYTES the cell's Zenoh transport drops the query (the querier times out) without
    buffering it; the same session's next query is answered."""
    for key in (f"{cell.root}/jobs/submit", f"{cell.root}/status"):
        replies = list(cell.session.get(key, payload=b"{" * (MAX_MESSAGE_BYTES + 1024), timeout=1.0))
        assert all(r.ok is None for r in replies)
        assert not any(r.err is not None and b'"code"' in r.err.payload.to_bytes() for r in replies)
    ok = cell.query(f"{cell.root}/status", b"")
    assert len(ok) == 1 and ok[0].ok is not None
