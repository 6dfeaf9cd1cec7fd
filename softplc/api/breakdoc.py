"""The OpenAPI description of the breakpoint and single-scan routes (api/debug.py).

Owns: their paths and schemas, merged into the document by openapi.py.
Does not know: aiohttp, the scan.
"""

from __future__ import annotations

from typing import Any


def _err(*codes: int) -> dict[str, Any]:
    return {str(c): {"description": "Error", "content": {"application/json": {
        "schema": {"$ref": "#/components/schemas/Error"}}}} for c in codes}


def _ok(summary: str) -> dict[str, Any]:
    return {"description": summary, "content": {"application/json": {"schema": {
        "type": "object", "properties": {"ok": {"type": "boolean"},
                                         "message": {"type": "string"},
                                         "state": {"type": "string"},
                                         "id": {"type": "integer"}}}}}}


def break_paths(prefix: str) -> dict[str, Any]:
    """The routes of breakpoints and single scans (docs/debug.md)."""
    point = {"type": "object", "properties": {
        "id": {"type": "integer"}, "on": {"type": "string", "enum": ["fire", "enabled", "when"]},
        "target": {"type": "string"}, "outputs": {"type": "string", "enum": ["hold", "safe"]},
        "text": {"type": "string"}}}
    pause = {"type": ["object", "null"], "properties": {
        "k": {"type": "integer"}, "scan_count": {"type": "integer"},
        "reason": {"type": "string"}, "breakpoints": {"type": "array", "items": point},
        "steps": {"type": "integer"}, "outputs": {"type": "string"}}}
    listing = {"type": "object", "properties": {
        "breakpoints": {"type": "array", "items": point}, "paused": pause,
        "steps_left": {"type": "integer"}, "scan_count": {"type": "integer"}}}
    add = {"type": "object", "properties": {
        "on": {"type": "string", "enum": ["fire", "enabled", "when"], "default": "fire"},
        "transition": {"type": "string"}, "condition": {"type": "string"},
        "outputs": {"type": "string", "enum": ["hold", "safe"], "default": "hold"}}}
    changed = _ok("Applied at the next scan boundary.")
    return {
        f"{prefix}/breakpoints": {
            "get": {"operationId": "breakpoints", "tags": ["debug"],
                    "summary": "The breakpoints, and the pause if the PLC is paused.",
                    "responses": {"200": {"description": "Breakpoints and pause.", "content": {
                        "application/json": {"schema": listing}}}, **_err(401, 403, 503)}},
            "post": {"operationId": "addBreakpoint", "tags": ["debug"],
                     "summary": "Pause at the end of the scan in which a transition fires, "
                                "becomes enabled, or a condition becomes true.",
                     "requestBody": {"required": True, "content": {
                         "application/json": {"schema": add}}},
                     "responses": {"200": changed, **_err(400, 401, 403, 409, 422, 503)}},
            "delete": {"operationId": "clearBreakpoints", "tags": ["debug"],
                       "summary": "Remove every breakpoint (a pause stays: continue ends it).",
                       "responses": {"200": changed, **_err(401, 403, 503)}}},
        f"{prefix}/breakpoints/{{id}}": {"delete": {
            "operationId": "removeBreakpoint", "tags": ["debug"],
            "summary": "Remove one breakpoint (b3 or 3).",
            "parameters": [{"name": "id", "in": "path", "required": True,
                            "schema": {"type": "string"}}],
            "responses": {"200": changed, **_err(401, 403, 404, 422, 503)}}},
        f"{prefix}/step": {"post": {
            "operationId": "step", "tags": ["debug"],
            "summary": "While paused: run exactly `scans` scans, then pause again.",
            "parameters": [{"name": "scans", "in": "query", "required": False,
                            "schema": {"type": "integer", "minimum": 1, "maximum": 1000000,
                                       "default": 1}}],
            "responses": {"200": changed, **_err(400, 401, 403, 409, 503)}}},
        f"{prefix}/continue": {"post": {
            "operationId": "continue", "tags": ["debug"],
            "summary": "While paused: run on until a breakpoint hits.",
            "responses": {"200": changed, **_err(401, 403, 409, 503)}}},
    }
