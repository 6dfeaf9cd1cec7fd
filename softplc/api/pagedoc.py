"""The operator's page in the API's description: its routes (the page and its static files,
the net, the live stream, forcing), for openapi.py.

Owns: LIVE_HZ (how often the live stream sends a frame at most) and the page's OpenAPI paths.
Does not know: how the routes are served (web.py).
"""

from __future__ import annotations

from typing import Any, Final

LIVE_HZ: Final = 25  # frames per second at most; the board itself refreshes about every 50 ms


def page_paths(prefix: str) -> dict[str, Any]:
    """web.py's routes (the page and static files included)."""
    def err(*codes: int) -> dict[str, Any]:
        return {str(c): {"description": "Error", "content": {"application/json": {
            "schema": {"$ref": "#/components/schemas/Error"}}}} for c in codes}

    result = {"200": {"description": "Accepted; `state` is the (unchanged) state.",
                      "content": {"application/json": {
                          "schema": {"$ref": "#/components/schemas/CommandResult"}}}}}
    name = {"name": "name", "in": "path", "required": True, "schema": {"type": "string"}}
    html = {"200": {"description": "HTML, JavaScript or CSS of the operator's page.",
                    "content": {"text/html": {"schema": {"type": "string"}}}}, **err(403, 404)}
    page = {"get": {"operationId": "page", "tags": ["page"], "security": [],
                    "summary": "The operator's page (served without a token; it asks for one).",
                    "responses": html}}
    return {
        "/": page,
        "/index.html": {"get": {**page["get"], "operationId": "pageIndex"}},
        "/static": {"get": {"operationId": "static", "tags": ["page"], "security": [],
                            "summary": "The page's vendored libraries (static/VENDORED.md).",
                            "responses": html}},
        f"{prefix}/net": {"get": {
            "operationId": "net", "tags": ["page"],
            "summary": "The loaded net's structure: places, transitions, arcs, subnet instance "
                       "of each, outputs, symbols with descriptions and how a value is shown "
                       "and given (core/present.py: scaled, unit, range, decimals).",
            "responses": {"200": {"description": "The structure.", "content": {
                "application/json": {"schema": {"type": "object"}}}}, **err(401, 403, 404, 503)}}},
        f"{prefix}/live": {"get": {
            "operationId": "live", "tags": ["page"],
            "summary": f"Server-sent `event: frame` JSON frames for pages, at most {LIVE_HZ}/s: "
                       "state, marking, busy firings, fire counts, values, forces, timing, "
                       "new events.",
            "responses": {"200": {"description": "An endless stream.", "content": {
                "text/event-stream": {"schema": {"type": "string"}}}}, **err(401, 403)}}},
        f"{prefix}/forces": {
            "get": {"operationId": "listForces", "tags": ["forcing"],
                    "summary": "Forced symbols and their values.",
                    "responses": {"200": {"description": "{forced: {symbol: value}}", "content": {
                        "application/json": {"schema": {"type": "object"}}}},
                        **err(401, 403, 503)}},
            "delete": {"operationId": "releaseAllForces", "tags": ["forcing"],
                       "summary": "Release every force.",
                       "responses": {**result, **err(401, 403, 409, 503)}}},
        f"{prefix}/forces/{{name}}": {
            "put": {"operationId": "force", "tags": ["forcing"], "parameters": [name],
                    "summary": "Force a symbol: an input replaces the driver's value at the "
                               "latch, an output the program's value (while RUNNING).",
                    "requestBody": {"required": True, "content": {"application/json": {
                        "schema": {"$ref": "#/components/schemas/SymbolWrite"}}}},
                    "responses": {**result, **err(400, 401, 403, 409, 413, 422, 503)}},
            "delete": {"operationId": "releaseForce", "tags": ["forcing"], "parameters": [name],
                       "summary": "Release one force.",
                       "responses": {**result, **err(401, 403, 409, 422, 503)}}},
    }
