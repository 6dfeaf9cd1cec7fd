"""Users (softplc/security/users.py), roles (roles.py) and the back-off (access.py), without a
server: scrypt hashes with their parameters and a salt each, a 0600 file replaced whole,
API keys stored hashed, the route table covering every served route."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from softplc.api.roles import ROUTE_ROLES, Role, required_role
from softplc.api.server import ApiServer
from softplc.security import users as users_module
from softplc.security.backoff import BACKOFF_ENTRIES, FREE_FAILURES, Backoff
from softplc.security.users import OWNER, UserError, UserStore, hash_password, password_matches


def test_password_hashes_are_scrypt_with_stated_parameters_and_a_salt_each() -> None:
    first, second = hash_password("correct horse"), hash_password("correct horse")
    assert first.startswith("$scrypt$ln=15,r=8,p=3$") and first != second  # salted
    assert "correct horse" not in first
    assert password_matches("correct horse", first) and password_matches("correct horse",
                                                                          second)
    assert not password_matches("correct hors", first)
    assert not password_matches("correct horse", "$scrypt$ln=99,r=8,p=3$AAAA$AAAA")
    assert not password_matches("correct horse", "garbage")
    import inspect
    assert "hmac.compare_digest" in inspect.getsource(password_matches)


def test_the_store_is_0600_replaced_whole_and_read_again_when_changed(tmp_path: Path) -> None:
    store = UserStore(tmp_path)
    store.add("op", Role.OPERATOR, "op-password")
    path = tmp_path / users_module.USERS_FILE
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert "op-password" not in path.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["users", "users.lock"]  # no temp left
    other = UserStore(tmp_path)  # another process's view
    assert other.verify("op", "op-password") is Role.OPERATOR
    assert other.verify("op", "wrong-password") is None
    assert other.verify("nobody", "op-password") is None
    store.set_role("op", Role.ENGINEER)
    assert other.verify("op", "op-password") is Role.ENGINEER
    store.set_password("op", "new-password")
    assert other.verify("op", "op-password") is None
    assert other.verify("op", "new-password") is Role.ENGINEER
    store.remove("op")
    assert other.verify("op", "new-password") is None


def test_api_keys_are_random_shown_once_and_stored_hashed(tmp_path: Path) -> None:
    store = UserStore(tmp_path)
    store.add("script", Role.OPERATOR, "a-long-password")
    key = store.new_key("script")
    assert key.startswith("script.") and len(key) > 40
    assert key.partition(".")[2] not in (tmp_path / "users").read_text()
    found = UserStore(tmp_path).verify_key(key)
    assert found is not None and found.name == "script" and found.role is Role.OPERATOR
    assert UserStore(tmp_path).verify_key(key[:-1] + ("A" if key[-1] != "A" else "B")) is None
    assert UserStore(tmp_path).verify_key("script") is None
    newer = store.new_key("script")
    assert UserStore(tmp_path).verify_key(key) is None  # the old one stops working
    store.revoke_key("script")
    assert UserStore(tmp_path).verify_key(newer) is None


def test_names_passwords_and_the_owner_are_checked(tmp_path: Path) -> None:
    store = UserStore(tmp_path)
    for name in ("", "Op", "a b", "x" * 33, "../etc", "op.x", OWNER):
        with pytest.raises(UserError):
            store.add(name, Role.VIEWER, "long-enough")
    with pytest.raises(UserError, match="8 to"):
        store.add("op", Role.VIEWER, "short")
    store.add("op", Role.VIEWER, "long-enough")
    with pytest.raises(UserError, match="exists"):
        store.add("op", Role.ADMIN, "long-enough")
    with pytest.raises(UserError, match="no user"):
        store.remove("nobody")
    with pytest.raises(ValueError, match="one of viewer, operator, engineer, admin"):
        Role.parse("root")


def test_an_unusable_users_file_is_an_error_naming_the_file_not_a_login(tmp_path: Path) -> None:
    (tmp_path / "users").write_text("{not json")
    with pytest.raises(UserError, match="unusable"):
        UserStore(tmp_path).verify("op", "whatever-password")


def test_every_served_route_is_in_the_role_table(tmp_path: Path) -> None:
    server = ApiServer(None, None, None, state_dir=tmp_path)  # type: ignore[arg-type]
    served = {("GET" if r.method == "HEAD" else r.method, r.resource.canonical)
              for r in server.build_app().router.routes() if r.resource is not None}
    assert served == set(ROUTE_ROLES), "routes without a role, or roles without a route"
    assert required_role("POST", "/api/v1/stop") is Role.OPERATOR
    assert required_role("POST", "/api/v1/kill") is Role.ENGINEER
    assert required_role("GET", "/api/v1/audit") is Role.ADMIN
    assert required_role("POST", "/api/v1/new-route-nobody-listed") is Role.ADMIN  # closed
    assert required_role("GET", None) is Role.VIEWER  # a 404 or 405 to read


def test_backoff_per_key_doubles_caps_and_forgets_the_oldest() -> None:
    now = [0.0]
    backoff = Backoff(lambda: now[0])
    user, peer = ("user", "op"), ("peer", "10.0.0.9")
    for _ in range(FREE_FAILURES):
        backoff.failed(user, peer)
        assert backoff.wait_s(user) == 0
    backoff.failed(user, peer)
    assert backoff.wait_s(user) == 1.0 and backoff.wait_s(peer) == 1.0
    assert backoff.wait_s(("user", "other")) == 0
    backoff.failed(user)
    assert backoff.wait_s(user) == 2.0
    for _ in range(20):
        backoff.failed(user)
    assert backoff.wait_s(user) == 60.0
    now[0] = 61.0
    assert backoff.wait_s(user) == 0
    backoff.succeeded(user)
    backoff.failed(user)
    assert backoff.wait_s(user) == 0  # counting again from the start
    for n in range(BACKOFF_ENTRIES + 10):
        backoff.failed(("peer", f"10.1.{n // 256}.{n % 256}"))
    assert len(backoff._table) == BACKOFF_ENTRIES
