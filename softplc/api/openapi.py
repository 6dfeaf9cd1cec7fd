"""The OpenAPI 3.1 description of the HTTP management service, as a plain dict.

Owns: the published contract (paths, parameters, status codes, schemas).
Does not know: aiohttp, handlers; tests check that every served route is described here.
"""

from __future__ import annotations

import copy
from typing import Any, Final

from softplc.api.accessdoc import access_paths
from softplc.api.breakdoc import break_paths
from softplc.api.debugdoc import debug_paths
from softplc.api.historydoc import history_paths
from softplc.api.pagedoc import page_paths

API_PREFIX: Final = "/api/v1"
LIFECYCLE_COMMANDS: Final = ("start", "stop", "resume", "reset", "kill")

_COMMAND_HELP: Final = {
    "start": "STOPPED -> RUNNING from the initial marking (cold start).",
    "stop": "RUNNING -> STOPPED: outputs to safe values, marking and timers frozen.",
    "resume": "STOPPED -> RUNNING with the kept marking (warm start).",
    "reset": "STOPPED/KILLED/FAULTED -> STOPPED with the initial marking.",
    "kill": "Immediate stop: the scan's outputs are not committed, outputs to safe values.",
}


def _ref(name: str) -> dict[str, str]:
    return {"$ref": f"#/components/schemas/{name}"}


def _json(schema: str, description: str) -> dict[str, Any]:
    return {"description": description, "content": {"application/json": {"schema": _ref(schema)}}}


def _errors(*codes: int) -> dict[str, Any]:
    text = {
        400: "Malformed request (bad flag, body not UTF-8 or not JSON).",
        401: "No credentials where the route needs more than the anonymous role, or wrong "
             "ones (docs/security.md, users and roles).",
        403: "Refused: a role too low for the route, cross-origin request, foreign Host "
             "header, or an input symbol.",
        404: "No such symbol or path.",
        409: "Refused by the program lifecycle in the current state, or expired (`outcome`): "
             "never applied.",
        413: "Request body larger than 1 MiB.",
        422: "Invalid program or value; `problems` lists every problem.",
        503: "Not sent, never applied: the PLC is not responding (stale) or its queue is full.",
    }
    return {str(code): _json("Error", text[code]) for code in codes}


def _command_path(command: str) -> dict[str, Any]:
    return {
        "post": {
            "operationId": command,
            "summary": _COMMAND_HELP[command],
            "tags": ["program"],
            "parameters": [_IDEMPOTENCY],
            "responses": {
                "200": _json("CommandResult", "Applied; `state` is the new state."),
                "202": _json("CommandPending", "No reply yet: applied before its deadline or "
                             "never; ask `outcome` for it."),
                **_errors(401, 403, 409, 503),
            },
        }
    }


_IDEMPOTENCY: Final = {
    "name": "Idempotency-Key", "in": "header", "required": False,
    "schema": {"type": "string", "pattern": r"^[\x21-\x7e]{1,64}$"},
    "description": "A retry with the same key returns the first attempt's outcome; the "
    "command is never sent twice."}


_PROGRAM: Final[dict[str, Any]] = {
    "post": {
        "operationId": "download",
        "summary": "Download a program: a bundle (application/zip: the program with its io "
        "image and subnets, docs/programs.md) or plain YAML text (resolved against the "
        "server's programs directory); validated completely before anything changes. While "
        "RUNNING it needs online=true (online change).",
        "tags": ["program"],
        "parameters": [
            {"name": "online", "in": "query", "schema": {"type": "boolean"},
             "description": "Online change: swap the net at a scan boundary, keep the marking."},
            {"name": "replace", "in": "query", "schema": {"type": "boolean"},
             "description": "While RUNNING, a program with another name on the same devices "
             "replaces the running one from its initial marking (refused without it)."},
            {"name": "dry_run", "in": "query", "schema": {"type": "boolean"},
             "description": "Compile and answer the plan (`plan`: kept, new and dropped "
             "places with tokens, outputs changing hands, verdict) against the running state; "
             "nothing is applied."},
            {"name": "allow_older", "in": "query", "schema": {"type": "boolean"},
             "description": "With trusted keys: take a program signed with a version older "
             "than the running one (a rollback, audited; refused without it)."},
            {"name": "X-Softplc-Online", "in": "header", "schema": {"type": "boolean"},
             "description": "Same as the `online` query parameter."},
            {"name": "name", "in": "query",
             "schema": {"type": "string", "pattern": r"^[A-Za-z0-9._-]{1,128}$"},
             "description": "File name of the program, used in problem messages."},
            _IDEMPOTENCY,
        ],
        "requestBody": {
            "required": True,
            "content": {
                media: {"schema": {"type": "string"}}
                for media in ("application/yaml", "text/yaml", "text/plain")
            } | {"application/zip": {"schema": {"type": "string", "format": "binary"}}},
        },
        "responses": {
            "200": _json("CommandResult", "Downloaded (or changed online)."),
            "202": _json("CommandPending", "No reply yet: applied before its deadline or never."),
            **_errors(400, 401, 403, 409, 413, 422, 503),
        },
    },
    "get": {
        "operationId": "upload",
        "summary": "The running program's bundle (application/zip), byte for byte as "
        "downloaded (`softplc upload`).",
        "tags": ["program"],
        "responses": {
            "200": {"description": "The bundle.",
                    "content": {"application/zip": {"schema": {"type": "string",
                                                               "format": "binary"}}}},
            **_errors(401, 404, 409),
        },
    },
}

_SYMBOL_NAME: Final = {"name": "name", "in": "path", "required": True, "schema": {"type": "string"}}

_SCHEMAS: Final[dict[str, Any]] = {
    "Error": {
        "type": "object",
        "required": ["error", "problems"],
        "properties": {
            "error": {"type": "string"},
            "problems": {"type": "array", "items": {"type": "string"},
                         "description": "Every problem, as FILE:LINE: path: message."},
            "state": {"type": "string"},
            "refusal": {"type": "string", "description": "Why a download was refused: "
                        "program, analysis, device, compiler, boot or sizes.",
                        "enum": ["program", "analysis", "device", "compiler", "boot", "sizes"]},
        },
    },
    "CommandResult": {
        "type": "object",
        "required": ["ok", "message", "state"],
        "properties": {"ok": {"type": "boolean"}, "message": {"type": "string"},
                       "id": {"type": "integer"},
                       "state": {"type": "string",
                                 "enum": ["EMPTY", "STOPPED", "RUNNING", "KILLED", "FAULTED"]}},
    },
    "CommandPending": {
        "type": "object",
        "required": ["id", "status", "outcome"],
        "properties": {"id": {"type": "integer"}, "pending": {"type": "boolean"},
                       "status": {"type": "string"}, "outcome": {"type": "string"},
                       "message": {"type": "string"}},
    },
    "CommandOutcome": {
        "type": "object",
        "required": ["id", "command", "status"],
        "properties": {
            "id": {"type": "integer"}, "command": {"type": "string"},
            "status": {"type": "string",
                       "enum": ["pending", "applied", "refused", "expired", "unknown"]},
            "message": {"type": "string"}, "state": {"type": ["string", "null"]},
            "deadline_in_ms": {"type": "integer"}},
    },
    "Status": {
        "type": "object",
        "required": ["state", "program", "program_hash", "scan_count", "marking", "timing"],
        "properties": {
            "state": {"type": "string"},
            "program": {"type": ["string", "null"]},
            "program_hash": {"type": ["string", "null"]},
            "scan_count": {"type": "integer"},
            "period_us": {"type": "integer"},
            "marking": {"type": "object", "additionalProperties": {}},
            "timing": {"type": "object", "properties": {
                "p99_lateness_us": {"type": "number"}, "overruns": {"type": "integer"}}},
            "health": {"type": "object", "additionalProperties": {"type": "string"}},
            "fault_code": {"type": "integer"},
            "fault_reason": {"type": ["string", "null"]},
            "devices": {"type": "object", "additionalProperties": {"type": "object"}},
            "start_mode": {"type": "string", "enum": ["cold", "warm"]},
            "start_reason": {"type": "string"},
            "boot_policy": {"type": "string", "enum": ["stop", "warm", "cold"]},
            "retain": {"type": ["object", "null"]},
            "diagnostics": {"type": "array", "items": {}},
            "last_event_seq": {"type": "integer"},
            "diagnostic_count": {"type": "integer",
                                 "description": "run-time errors of guards and actions so far"},
            "tokens": {"type": "object", "description": "coloured places' token records "
                       "(the first 20 of each)",
                       "additionalProperties": {"type": "array", "items": {"type": "object"}}},
            "analysis": {"type": ["object", "null"],
                         "description": "the verification gate's findings for the program"},
            "stale": {"type": "boolean",
                      "description": "the scan process has not published for too long"},
            "snapshot_age_ms": {"type": ["number", "null"]},
            "restarts": {"type": "integer",
                         "description": "scan process restarts by the supervisor"},
            "restart_reason": {"type": "string"},
            "scan_pid": {"type": "integer"},
            "compile_process": {
                "type": ["object", "null"],
                "description": "the scan process's compile process (runtime/compileproc.py): "
                               "pid now, processes started, why the last one ended while "
                               "compiling (empty: never)",
                "properties": {"pid": {"type": ["integer", "null"]},
                               "started": {"type": "integer"},
                               "last_failure": {"type": "string"}}},
            "forced": {"type": "object", "description": "forced symbols and their values",
                       "additionalProperties": {"type": "integer"}},
        },
    },
    "Symbol": {
        "type": "object",
        "required": ["name", "address", "type", "direction", "value"],
        "properties": {
            "name": {"type": "string"}, "address": {"type": "string"},
            "type": {"type": "string", "enum": ["bool", "word"]},
            "direction": {"type": "string", "enum": ["in", "out", "memory"]},
            "value": {"type": ["boolean", "integer"]},
            "raw": {"type": ["integer", "null"]},
        },
    },
    "Symbols": {
        "type": "object",
        "properties": {"snapshot_seq": {"type": "integer"},
                       "symbols": {"type": "object", "additionalProperties": _ref("Symbol")}},
    },
    "SymbolWrite": {
        "type": "object",
        "required": ["value"],
        "properties": {"value": {"type": ["boolean", "integer"], "minimum": 0,
                                 "maximum": 65535}},
    },
    "WriteQueued": {
        "type": "object",
        "properties": {"name": {"type": "string"}, "address": {"type": "string"},
                       "value": {"type": ["boolean", "integer"]}, "queued": {"type": "boolean"}},
    },
}


def openapi_document() -> dict[str, Any]:
    """A fresh copy of the description (callers may add `servers`)."""
    paths: dict[str, Any] = {
        "/healthz": {"get": {
            "operationId": "healthz", "summary": "Liveness; never needs a token.",
            "security": [], "tags": ["service"],
            "responses": {"200": {"description": "The service answers.", "content": {
                "application/json": {"schema": {"type": "object"}}}}}}},
        f"{API_PREFIX}/status": {"get": {
            "operationId": "status", "tags": ["status"],
            "summary": "State, program and hash, scan count, timing, overruns, marking.",
            "responses": {"200": _json("Status", "The last status board."),
                          **_errors(401, 403, 503)}}},
        f"{API_PREFIX}/program": _PROGRAM,
        **{f"{API_PREFIX}/{c}": _command_path(c) for c in LIFECYCLE_COMMANDS},
        f"{API_PREFIX}/commands/{{id}}": {"get": {
            "operationId": "commandOutcome", "tags": ["program"],
            "summary": "The outcome of a recent command (by the id of its reply).",
            "parameters": [{"name": "id", "in": "path", "required": True,
                            "schema": {"type": "integer"}}],
            "responses": {"200": _json("CommandOutcome", "The command's outcome."),
                          **_errors(401, 403, 404)}}},
        f"{API_PREFIX}/symbols": {"get": {
            "operationId": "listSymbols", "tags": ["symbols"],
            "summary": "Every symbol of the loaded program with its live value.",
            "responses": {"200": _json("Symbols", "All symbols."), **_errors(401, 403, 503)}}},
        f"{API_PREFIX}/symbols/{{name}}": {
            "get": {"operationId": "readSymbol", "tags": ["symbols"],
                    "parameters": [_SYMBOL_NAME], "summary": "One symbol and its live value.",
                    "responses": {"200": _json("Symbol", "The symbol."),
                                  **_errors(401, 403, 404, 503)}},
            "put": {"operationId": "writeSymbol", "tags": ["symbols"],
                    "parameters": [_SYMBOL_NAME],
                    "summary": "Journal a write, applied at the next scan start like an HMI "
                    "write. Inputs are refused.",
                    "requestBody": {"required": True, "content": {
                        "application/json": {"schema": _ref("SymbolWrite")}}},
                    "responses": {"202": _json("WriteQueued", "Queued for the next scan."),
                                  **_errors(400, 401, 403, 404, 413, 422, 503)}}},
        f"{API_PREFIX}/events": {"get": {
            "operationId": "events", "tags": ["events"],
            "summary": "Server-sent events: one `data:` JSON {seq, scan, t_ns, name} per new "
            "event, `id:` = seq; a `: heartbeat` comment every 15 s; `event: overflow` when a "
            "slow client lost events.",
            "parameters": [
                {"name": "names", "in": "query", "schema": {"type": "string"},
                 "description": "Comma-separated event names to receive (default: all)."},
                {"name": "Last-Event-ID", "in": "header", "schema": {"type": "integer"},
                 "description": "Resume: also send retained events with a larger seq."},
            ],
            "responses": {"200": {"description": "An endless event stream.",
                                  "content": {"text/event-stream": {"schema": {"type": "string"}}}},
                          **_errors(400, 401, 403)}}},
        f"{API_PREFIX}/openapi.json": {"get": {
            "operationId": "openapi", "tags": ["service"], "summary": "This document.",
            "responses": {"200": {"description": "OpenAPI 3.1", "content": {
                "application/json": {"schema": {"type": "object"}}}}, **_errors(401, 403)}}},
    }
    paths.update(page_paths(API_PREFIX))  # the page, live stream and forcing
    paths.update(debug_paths(API_PREFIX))  # why (docs/debug.md)
    paths.update(break_paths(API_PREFIX))  # breakpoints, step, continue (docs/debug.md)
    paths.update(history_paths(API_PREFIX))  # the recent past (docs/debug.md)
    paths.update(access_paths(API_PREFIX))  # login, logout, whoami, audit
    return copy.deepcopy({
        "openapi": "3.1.0",
        "info": {"title": "softplc management API", "version": "1.0.0",
                 "description": "Program handling, status, symbols and events of one softplc. "
                 "See docs/api.md."},
        "paths": paths,
        "components": {
            "schemas": _SCHEMAS,
            "securitySchemes": {
                "bearer": {"type": "http", "scheme": "bearer",
                           "description": "A user's API key (softplc users key NAME), or the "
                           "owner's STATE_DIR/api_token."},
                "basic": {"type": "http", "scheme": "basic",
                          "description": "A user's name and password."}},
        },
        "security": [{"bearer": []}, {"basic": []}],
    })
