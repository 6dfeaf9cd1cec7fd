"""What each client session is told, where asyncua answers the same for everyone or not as
the spec says (issue 29).

Owns: the Read answer per session (UserAccessLevel without the write bits for a role below
the one symbol writes need, UserExecutable false on a method the session's role may not call:
access.py's table; the timestamps the request asked for), Republish as
Part 4 says (BadSubscriptionIdInvalid for a subscription the session does not hold,
BadMessageNotAvailable for a message no longer kept: asyncua 2.1.0 answers Good and an empty
message, so a client whose server restarted republishes for ever instead of re-creating its
subscriptions).
Does not know: the address space layout, the channel, which symbols exist (server.py does).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Awaitable, Callable
from functools import cache, partial
from typing import Final

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.server.internal_session import InternalSession

from softplc.opcua.access import METHOD_ACTS, decide
from softplc.security.roles import Act

# The AccessLevel bits that let a session change something (Part 3, AccessLevelType).
_WRITE_BITS: Final = sum(1 << int(bit) for bit in (
    ua.AccessLevel.CurrentWrite, ua.AccessLevel.HistoryWrite, ua.AccessLevel.StatusWrite,
    ua.AccessLevel.TimestampWrite))

Reader = Callable[[ua.ReadParameters], Awaitable[list[ua.DataValue]]]
MethodOf = Callable[[ua.NodeId], str | None]  # a method node -> its program method, if one


def hook(session: InternalSession, method_of: MethodOf) -> None:
    """Wrap `session`'s Read and Republish (asyncua's own session keeps its behaviour)."""
    session.read = partial(read, session, session.read, method_of)  # type: ignore[method-assign]
    session.republish = partial(republish, session,  # type: ignore[method-assign]
                                session.republish)


async def read(session: InternalSession, inner: Reader, method_of: MethodOf,
               params: ua.ReadParameters) -> list[ua.DataValue]:
    results = await inner(params)
    wanted = params.TimestampsToReturn
    # Each act decided once per Read (the users file looked at once), not once per node.
    allowed = cache(lambda act: decide(session, act).allowed)
    return [_told(item, value, allowed, method_of, wanted)
            for item, value in zip(params.NodesToRead, results, strict=True)]


def _told(item: ua.ReadValueId, value: ua.DataValue, allowed: Callable[[Act], bool],
          method_of: MethodOf, wanted: ua.TimestampsToReturn) -> ua.DataValue:
    attribute = item.AttributeId
    if attribute == ua.AttributeIds.Value:
        return _timestamps(value, wanted)
    if value.Value is None:
        return value
    if attribute == ua.AttributeIds.UserAccessLevel and isinstance(value.Value.Value, int) \
            and not allowed(Act.WRITE):
        level = value.Value.Value & ~_WRITE_BITS
        return dataclasses.replace(value, Value=ua.Variant(level, ua.VariantType.Byte))
    if attribute == ua.AttributeIds.UserExecutable and value.Value.Value is True:
        method = method_of(item.NodeId)
        if not allowed(METHOD_ACTS.get(method or "", Act.ADMINISTER)):
            return dataclasses.replace(value, Value=ua.Variant(False, ua.VariantType.Boolean))
    return value


def _timestamps(value: ua.DataValue, wanted: ua.TimestampsToReturn) -> ua.DataValue:
    """Part 4 (TimestampsToReturn): only the timestamps asked for; Invalid is refused by the
    stack before this point in spec terms, asyncua lets it through: answered as Neither."""
    source = wanted in (ua.TimestampsToReturn.Source, ua.TimestampsToReturn.Both)
    server = wanted in (ua.TimestampsToReturn.Server, ua.TimestampsToReturn.Both)
    if source and server:
        return value
    return dataclasses.replace(
        value, SourceTimestamp=value.SourceTimestamp if source else None,
        SourcePicoseconds=value.SourcePicoseconds if source else None,
        ServerTimestamp=value.ServerTimestamp if server else None,
        ServerPicoseconds=value.ServerPicoseconds if server else None)


def republish(session: InternalSession,
              inner: Callable[[ua.RepublishParameters], ua.NotificationMessage],
              params: ua.RepublishParameters) -> ua.NotificationMessage:
    """A ServiceError becomes the ServiceFault with its code (asyncua's uaprocessor)."""
    subscription = session.subscription_service.subscriptions.get(params.SubscriptionId)
    if subscription is None or subscription.session_id != session.session_id:
        raise ServiceError(ua.StatusCodes.BadSubscriptionIdInvalid)
    if params.RetransmitSequenceNumber not in subscription._not_acknowledged_results:
        raise ServiceError(ua.StatusCodes.BadMessageNotAvailable)
    return inner(params)
