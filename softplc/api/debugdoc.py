"""The debugging routes in the API's description (issue 32), for openapi.py.

Owns: the OpenAPI paths of debug.py's routes. Does not know: how they are served.
"""

from __future__ import annotations

from typing import Any


def debug_paths(prefix: str) -> dict[str, Any]:
    """debug.py's routes."""
    def err(*codes: int) -> dict[str, Any]:
        return {str(c): {"description": "Error", "content": {"application/json": {
            "schema": {"$ref": "#/components/schemas/Error"}}}} for c in codes}

    reason = {"type": "object", "required": ["kind", "text"], "properties": {
        "kind": {"type": "string", "enum": ["tokens", "test", "inhibitor", "capacity", "busy",
                                            "guard", "delay", "conflict", "forced", "fires",
                                            "fault"]},
        "text": {"type": "string"}, "place": {"type": "string"},
        "symbols": {"type": "array", "items": {"type": "string"}}}}
    why = {"type": "object", "required": ["transition", "verdict", "fires", "reasons"],
           "properties": {
               "transition": {"type": "string"},
               "verdict": {"type": "string",
                           "enum": ["fires", "blocked", "waiting", "lost", "error"]},
               "fires": {"type": "boolean"},
               "reasons": {"type": "array", "items": reason},
               "feeders": {"type": "array", "items": {"type": "object"},
                           "description": "the same, for the transitions that put tokens on "
                                          "a place it lacks"},
               "program": {"type": "string"}, "state": {"type": ["string", "null"]},
               "scan": {"type": "integer"}, "basis": {"type": "string"},
               "note": {"type": "string"}}}
    return {f"{prefix}/why/{{transition}}": {"get": {
        "operationId": "why", "tags": ["debug"],
        "summary": "Why a transition fires or not in the next firing round: places short of "
                   "tokens, inhibitor and test arcs, capacities, a timed firing in progress, "
                   "the guard with the values it read, an enabling delay, a conflict lost, "
                   "forced values (docs/debug.md).",
        "parameters": [{"name": "transition", "in": "path", "required": True,
                        "schema": {"type": "string"}}],
        "responses": {"200": {"description": "The verdict and its reasons.", "content": {
            "application/json": {"schema": why}}}, **err(401, 403, 404, 409, 503)}}}}
