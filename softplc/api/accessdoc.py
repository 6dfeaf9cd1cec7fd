"""The routes of access in the API's description (login, logout, whoami, audit and its
stream), for openapi.py.

Owns: their OpenAPI paths. Does not know: how they are served (accessroutes.py).
"""

from __future__ import annotations

from typing import Any


def access_paths(prefix: str) -> dict[str, Any]:
    def err(*codes: int) -> dict[str, Any]:
        return {str(c): {"description": "Error", "content": {"application/json": {
            "schema": {"$ref": "#/components/schemas/Error"}}}} for c in codes}

    def ok(description: str, properties: dict[str, Any]) -> dict[str, Any]:
        return {"200": {"description": description, "content": {"application/json": {
            "schema": {"type": "object", "properties": properties}}}}}

    text = {"type": ["string", "null"]}
    who = {"user": text, "role": text, "via": {"type": "string"}}
    return {
        f"{prefix}/login": {"post": {
            "operationId": "login", "tags": ["access"], "security": [],
            "summary": "User and password (JSON or HTTP Basic) -> a session cookie "
                       "(HttpOnly, SameSite=Strict; Secure over TLS) for the page.",
            "requestBody": {"required": False, "content": {"application/json": {"schema": {
                "type": "object", "required": ["user", "password"],
                "properties": {"user": {"type": "string"}, "password": {"type": "string"}}}}}},
            "responses": {**ok("Logged in.", {"user": text, "role": text}),
                          **err(400, 401, 403, 413, 429)}}},
        f"{prefix}/logout": {"post": {
            "operationId": "logout", "tags": ["access"], "security": [],
            "summary": "End the session of the cookie sent (if any).",
            "responses": {**ok("Logged out.", {"ok": {"type": "boolean"}}), **err(403)}}},
        f"{prefix}/whoami": {"get": {
            "operationId": "whoami", "tags": ["access"],
            "summary": "Who the request's credentials say it is, and the role they give.",
            "responses": {**ok("The principal.", who), **err(401, 403, 429)}}},
        f"{prefix}/audit": {"get": {
            "operationId": "audit", "tags": ["access"],
            "summary": "The audit trail (admin): the newest records and the chain's verdict.",
            "parameters": [
                {"name": "since", "in": "query", "schema": {"type": "string"},
                 "description": "ISO time (UTC unless a zone is given) or a duration back "
                                "from now (2h)."},
                {"name": "limit", "in": "query",
                 "schema": {"type": "integer", "minimum": 1, "maximum": 10000},
                 "description": "At most this many, the newest (default 1000)."}],
            "responses": {**ok("Records and verdict.", {
                "records": {"type": "array", "items": {"type": "object"}},
                "chain": {"type": "object"}}), **err(400, 401, 403, 429)}}},
        f"{prefix}/audit/events": {"get": {
            "operationId": "auditEvents", "tags": ["access"],
            "summary": "The audit trail as server-sent events (admin): one `data:` record per "
                       "line with `id:` = its seq, from now (or after Last-Event-ID); "
                       "`event: overflow` counts records skipped, `event: end` says why the "
                       "stream ends (the credentials no longer give admin).",
            "parameters": [
                {"name": "Last-Event-ID", "in": "header", "schema": {"type": "integer"},
                 "description": "Resume: the records after this seq still kept."}],
            "responses": {"200": {"description": "Record stream.", "content": {
                "text/event-stream": {"schema": {"type": "string"}}}},
                **err(400, 401, 403, 429, 503)}}},
    }
