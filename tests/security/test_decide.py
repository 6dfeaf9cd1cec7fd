"""The decision points on their own (security/decide.py, security/roles.py, issue 38): fast,
no sockets. Every way of proving an identity, the role it holds *now*, and the one-line reason
of a refusal; the act -> role table as the contract every door maps onto."""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.core.lifecycle import Command
from softplc.security.decide import Authority, Decision, Identity, anonymous, granted
from softplc.security.roles import COMMAND_ROLES, Act, Role, needs
from softplc.security.users import UserStore

PASSWORD = "operator-pass-1"
FAST = 10  # scrypt's log N for the test users: the rule, not the cost, is tested here


@pytest.fixture
def store(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> UserStore:
    monkeypatch.setattr("softplc.security.users.SCRYPT_LOG_N", FAST)
    users = UserStore(tmp_path)
    users.add("op", Role.OPERATOR, PASSWORD)
    users.add("eng", Role.ENGINEER, "engineer-pass-1")
    return users


@pytest.fixture
def owner_key() -> list[str]:
    return ["the-owners-key-0123456789"]


@pytest.fixture
def authority(store: UserStore, owner_key: list[str]) -> Authority:
    return Authority(store, lambda: owner_key[0])


def test_the_act_role_table_is_the_contract_of_every_door() -> None:
    expected = {
        Act.READ: Role.VIEWER,
        Act.WRITE: Role.OPERATOR, Act.START: Role.OPERATOR, Act.STOP: Role.OPERATOR,
        Act.RESUME: Role.OPERATOR,
        Act.DOWNLOAD: Role.ENGINEER, Act.RESET: Role.ENGINEER, Act.KILL: Role.ENGINEER,
        Act.FORCE: Role.ENGINEER, Act.UNFORCE: Role.ENGINEER, Act.BREAK: Role.ENGINEER,
        Act.UNBREAK: Role.ENGINEER, Act.STEP: Role.ENGINEER, Act.CONTINUE: Role.ENGINEER,
        Act.AUDIT: Role.ADMIN, Act.ADMINISTER: Role.ADMIN,
    }
    assert expected == COMMAND_ROLES, "doors and clients rely on who may do what"
    assert all(needs(act) is role for act, role in expected.items())
    for command in Command:  # a lifecycle command's act keeps its wire name
        assert Act.of(command).value == command.value
    assert [r.label for r in sorted(Role)] == ["viewer", "operator", "engineer", "admin"]
    assert Role.VIEWER < Role.OPERATOR < Role.ENGINEER < Role.ADMIN
    assert Role.parse(" Engineer ") is Role.ENGINEER
    with pytest.raises(ValueError, match="unknown role 'boss': one of viewer, operator"):
        Role.parse("boss")


def test_a_password_proves_a_user_whose_role_is_looked_up_at_every_decision(
        authority: Authority, store: UserStore) -> None:
    assert authority.by_password("op", "wrong-password") is None
    assert authority.by_password("nobody", PASSWORD) is None
    who = authority.by_password("op", PASSWORD)
    assert who is not None and (who.user, who.via) == ("op", "password")
    assert authority.decide(who, Act.STOP).allowed
    refused = authority.decide(who, Act.DOWNLOAD)
    assert not refused.allowed and refused.role is Role.OPERATOR
    assert refused.reason() == "download needs engineer; op has operator"
    store.set_role("op", Role.ENGINEER)
    assert authority.decide(who, Act.DOWNLOAD).allowed  # promoted: at once
    store.set_password("op", "another-pass-1")
    changed = authority.decide(who, Act.READ)
    assert not changed.allowed and changed.role is None
    assert changed.reason() == ("read needs viewer; op has no role (the password was "
                                "changed)")


def test_a_removed_user_holds_nothing(authority: Authority, store: UserStore) -> None:
    who = authority.by_password("eng", "engineer-pass-1")
    assert who is not None and authority.decide(who, Act.KILL).allowed
    store.remove("eng")
    assert authority.role_now(who) == (None, "the user was removed")
    assert not authority.decide(who, Act.READ).allowed


def test_an_api_key_holds_while_it_is_the_users_key(authority: Authority,
                                                    store: UserStore) -> None:
    key = store.new_key("op")
    assert authority.by_key(key[:-1] + ("A" if key[-1] != "A" else "B")) is None
    assert authority.by_key("op") is None and authority.by_key("") is None
    who = authority.by_key(key)
    assert who is not None and (who.user, who.via) == ("op", "key")
    assert authority.role_now(who) == (Role.OPERATOR, "")
    store.new_key("op")  # replaced: the old one's identity holds nothing
    assert authority.role_now(who) == (None, "the API key was replaced or revoked")
    assert authority.by_key(key) is None


def test_the_owner_is_admin_while_the_key_is_the_owners(authority: Authority,
                                                       owner_key: list[str]) -> None:
    assert authority.owner("") is None and authority.owner("not-the-key") is None
    who = authority.owner(owner_key[0])
    assert who is not None and (who.user, who.via) == ("owner", "owner")
    assert authority.decide(who, Act.ADMINISTER).allowed
    owner_key[0] = "a-new-owners-key-98765"
    assert authority.role_now(who) == (None, "the owner's key was replaced")


def test_granted_identities_hold_what_their_door_grants(authority: Authority) -> None:
    viewer = anonymous(Role.VIEWER)
    assert authority.role_now(viewer) == (Role.VIEWER, "")
    assert authority.decide(viewer, Act.READ).allowed
    no_one = authority.decide(anonymous(None), Act.READ)
    assert not no_one.allowed
    assert no_one.reason() == "read needs viewer; a client without credentials has no role"
    panel = Identity("panel-7", "certificate", granted=Role.OPERATOR)
    assert granted(panel, Act.WRITE).allowed and not granted(panel, Act.DOWNLOAD).allowed
    policy = Identity(None, "policy", granted=Role.VIEWER)
    assert not granted(policy, Act.WRITE).allowed
    proven = Identity("op", "password", "hash")
    assert granted(proven, Act.READ) == Decision(proven, Act.READ, Role.VIEWER, None,
                                                 "no users file at this door")
    assert authority.role_now(Identity("op", "telepathy")) == (None, "unknown proof "
                                                                "'telepathy'")


def test_an_unusable_users_file_leaves_only_the_owner(authority: Authority, store: UserStore,
                                                      owner_key: list[str]) -> None:
    who = authority.by_password("op", PASSWORD)
    assert who is not None
    store.path.write_text("{not json", encoding="utf-8")
    assert authority.known() == {}
    assert authority.role_now(who)[0] is None
    assert authority.by_password("op", PASSWORD) is None
    owner = authority.owner(owner_key[0])
    assert owner is not None and authority.decide(owner, Act.KILL).allowed
