"""The pure pieces of issue 27's defences: the JSON structure scan (depth, keys, items, tokens), the
capped validation errors, the CSV formula escaping and the access log's token redaction."""

from __future__ import annotations

import csv
import io
import json
import logging

import pytest
from fastapi.exceptions import RequestValidationError

from api.accesslog import RedactTokens, redact
from api.bodies import JsonTooComplex, cap_errors, check_json, parse_json
from api.problems import validation_errors
from services.experiments.results import escape_cell
from services.settings import Limits

LIMITS = Limits(json_depth=8, json_keys=20, json_items=50, json_tokens=1000)


def test_a_body_within_the_limits_parses():
    body = {"a": [1, 2, {"b": "x,y]}{\\\"" * 3}], "c": "[" * 100, "d": {"e": [[[1]]]}}
    assert parse_json(json.dumps(body).encode(), LIMITS) == body


@pytest.mark.parametrize("body, limit", [
    ("[" * 9 + "]" * 9, "json_depth"),
    (json.dumps({f"k{i}": i for i in range(21)}), "json_keys"),
    (json.dumps(list(range(51))), "json_items"),
    (json.dumps([list(range(40)) for _ in range(30)]), "json_tokens"),
    ('"a"' * 1001, "json_tokens"),                     # not JSON: still bounded, never parsed
])
def test_each_limit_is_named(body, limit):
    with pytest.raises(JsonTooComplex) as err:
        check_json(body.encode(), LIMITS)
    assert err.value.limit == limit and f"NDRF_MAX_{limit.upper()}" in str(err.value)


def test_strings_hide_their_structure_characters():
    check_json(json.dumps({"xml": "[{,}]" * 10_000}).encode(), LIMITS)   # one token, whatever it contains


def test_the_scan_stops_at_the_first_limit_whatever_the_size():
    limits = Limits()
    body = json.dumps(["x"] * 1_000_000).encode()                  # '["x", "x", ...]': 5 bytes an item
    with pytest.raises(JsonTooComplex) as err:
        check_json(body, limits)
    # Stopped at the comma after item json_items (offset 5 n - 1), 1 % of the way into the body
    assert err.value.limit == "json_items" and err.value.position == 5 * limits.json_items - 1
    assert body[err.value.position:err.value.position + 1] == b","
    # Decided by the bytes up to there: what follows (more items, or no valid JSON at all: a
    # parse-first check would fail on it) is never read
    for tail in (b', "x"' * 1_000_000 + b"]", b"", b"\xff{{[[\"unterminated"):
        with pytest.raises(JsonTooComplex) as again:
            check_json(body[:err.value.position + 1] + tail, limits)
        assert (again.value.limit, again.value.position) == (err.value.limit, err.value.position)
    big = json.dumps({"data": "A" * (60 << 20)}).encode()          # a large upload is one long string
    assert check_json(big, limits) == 4                              # {, "data", the string, }


def test_validation_errors_are_capped_with_a_count():
    errors = [{"loc": ("body", "values", i), "msg": "bad", "input": "x" * 100} for i in range(1000)]
    exc = cap_errors(errors, 1000, 20)
    assert len(exc.errors()) == 20 and "input" not in exc.errors()[0]
    listed, more = validation_errors(exc, 20)
    assert listed[0] == ("values[0]", "bad") and len(listed) == 20 and more == 980
    plain = RequestValidationError([{"loc": ("query", "limit"), "msg": "too big"}] * 3)
    assert validation_errors(plain, 20) == ([("query.limit", "too big")], 0)   # duplicates listed once, not counted


@pytest.mark.parametrize("text, escaped", [
    ("=1+2", "'=1+2"), ("+cmd|' /C calc'!A0", "'+cmd|' /C calc'!A0"), ("-2+3", "'-2+3"), ("@SUM(A1)", "'@SUM(A1)"),
    ("\t=1", "'\t=1"), ("\r=1", "'\r=1"), ("-0.5", "-0.5"), ("+1e-3", "+1e-3"), ("prb", "prb"), ("", ""),
])
def test_csv_cells_are_escaped_against_formulas(text, escaped):
    assert escape_cell(text) == escaped
    assert escape_cell(0.25) == 0.25 and escape_cell(-3) == -3


def test_results_csv_escapes_names_and_values():
    from schemas.experiments import RunRow
    from services.experiments.results import results_csv

    rows = [RunRow(index=0, status="failed", seed=1, varied={"=HYPERLINK(\"x\")": "+cmd|' /C calc'!A0", "lr": -0.5},
                   error="=1+2,\n@x", final_loss=-1.5, iterations=3)]
    text = results_csv(rows)
    table = list(csv.reader(io.StringIO(text)))
    assert table[0][4] == "'=HYPERLINK(\"x\")" and table[1][4] == "'+cmd|' /C calc'!A0"
    assert table[1][5] == "-0.5" and table[1][table[0].index("error")] == "'=1+2,\n@x"
    assert "final_loss" in table[0] and table[1][table[0].index("final_loss")] == "-1.5"
    cells = [cell for line in table for cell in line]
    assert not any(cell.startswith(("=", "+", "@", "\t", "\r")) for cell in cells)


def test_tokens_are_redacted_from_access_log_records():
    assert redact("/v1/jobs/j1/events?token=j1.123.abc&after=3") == "/v1/jobs/j1/events?token=REDACTED&after=3"
    assert redact("/v1/jobs/j1?after=1&TOKEN=x") == "/v1/jobs/j1?after=1&TOKEN=REDACTED"
    for name in ("tok%65n", "%74oken", "%54OKEN", "access%5ftoken"):           # names percent-encoded
        assert redact(f"/v1/jobs/j1?a=1&{name}=secret&b=2") == f"/v1/jobs/j1?a=1&{name}=REDACTED&b=2", name
    assert redact("/v1/jobs/j1?after=3&tokens=kept") == "/v1/jobs/j1?after=3&tokens=kept"
    record = logging.LogRecord("uvicorn.access", logging.INFO, __file__, 1, '%s - "%s %s HTTP/%s" %d',
                               ("127.0.0.1:1", "GET", "/v1/jobs/j?token=secret", "1.1", 200), None)
    assert RedactTokens().filter(record) and "secret" not in record.getMessage()
