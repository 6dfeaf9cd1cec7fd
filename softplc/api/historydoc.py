"""The history route in the API's description (issue 32), for openapi.py.

Owns: the OpenAPI path of history.py's route. Does not know: how it is served.
"""

from __future__ import annotations

from typing import Any


def history_paths(prefix: str) -> dict[str, Any]:
    """history.py's route."""
    def err(*codes: int) -> dict[str, Any]:
        return {str(c): {"description": "Error", "content": {"application/json": {
            "schema": {"$ref": "#/components/schemas/Error"}}}} for c in codes}

    ints = {"type": "array", "items": {"type": "integer"}}
    times = {"type": "array", "items": {"type": "number"}, "description": "Unix time, ms"}
    board = {"type": "object", "properties": {
        "scans": ints, "t_ms": times,
        "marking": {"type": "object", "additionalProperties": ints},
        "fired": {"type": "array", "items": {"type": ["object", "null"]},
                  "description": "transition -> times fired since the previous sample"},
        "forced": {"type": "array", "items": {"type": "object"}}}}
    window = {"type": "object", "required": ["scans", "t_ms", "values", "gaps", "board"],
              "properties": {
                  "program": {"type": "string"}, "program_hash": {"type": "string"},
                  "since": {"type": "integer"}, "scans": ints, "t_ms": times,
                  "state": {"type": "array", "items": {"type": "string"}},
                  "forced_count": ints,
                  "values": {"type": "object", "additionalProperties": {"type": "array"},
                             "description": "symbol -> its typed value at each scan"},
                  "types": {"type": "object", "additionalProperties": {"type": "string"}},
                  "gaps": {"type": "array", "items": ints,
                           "description": "[first, last] scans not sampled"},
                  "oldest_scan": {"type": ["integer", "null"]}, "board": board,
                  "sampling": {"type": "string"}, "capacity": {"type": "object"}}}
    names = {"type": "string", "description": "comma-separated; default: the first 64"}
    return {f"{prefix}/history": {"get": {
        "operationId": "history", "tags": ["debug"],
        "summary": "The recent past: the last scans' symbol values, states and forces, and the "
                   "marking, fired transitions and forces of the status board samples among "
                   "them, with the scans not sampled (docs/debug.md).",
        "parameters": [
            {"name": "since", "in": "query", "schema": {"type": "integer"},
             "description": "only scans after this one"},
            {"name": "symbols", "in": "query", "schema": names},
            {"name": "places", "in": "query", "schema": names}],
        "responses": {"200": {"description": "The window.", "content": {
            "application/json": {"schema": window}}}, **err(400, 401, 403, 404, 503)}}}}
