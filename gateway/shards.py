"""Several gateway processes sharing the subjects of one network.

When one process (or one machine) cannot solve every body, gateways started
with ``--share`` split the subjects among themselves with no coordinator:
each declares a liveliness token ``@bodynet/gateways/<id>`` and watches the
others', and every gateway computes the same assignment from the same set of
live ids by rendezvous (highest random weight) hashing: a subject belongs to
the gateway whose ``hash(id, subject)`` is highest. So no subject is served
twice once the gateways see the same members (a token comes or goes within
milliseconds), none is left out, and when a gateway comes or goes only the
subjects that were or become its own move; a dead gateway's token vanishes
when its link closes and the survivors take its subjects at their next sample.

This module is the pure part: the members and who owns what. The gateway
(``gateway/service.py``) holds the token and feeds the members in.
"""

from __future__ import annotations

import hashlib
import os
import socket
import uuid
from collections.abc import Iterable

from bodynet.core.keys import KeySpaceError, chunk


def new_id() -> str:
    """A gateway id unique on the network: host, process and a random part."""
    host = "".join(c if c.isalnum() or c in "-_" else "-" for c in socket.gethostname())
    return f"{host or 'host'}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


def check_id(gateway_id: str) -> str:
    """``gateway_id`` if it can be one chunk of a key, else ``KeySpaceError``."""
    if not gateway_id or chunk(gateway_id) != gateway_id:
        raise KeySpaceError(
            f"gateway id {gateway_id!r} must be one key chunk of letters, digits, '-', '_' or '.'"
        )
    return gateway_id


def weight(gateway_id: str, subject: str | None) -> int:
    """The rendezvous weight of a subject at a gateway (the same on every machine)."""
    text = f"{gateway_id}\0{subject or ''}".encode()
    return int.from_bytes(hashlib.blake2b(text, digest_size=8).digest(), "big")


def owner(members: Iterable[str], subject: str | None) -> str | None:
    """The gateway that serves ``subject`` among ``members`` (None if there are none)."""
    return max(members, key=lambda m: (weight(m, subject), m), default=None)


class Share:
    """One gateway's view of its group: its own id and the live members'."""

    def __init__(self, gateway_id: str) -> None:
        self.id = check_id(gateway_id)
        self.members: set[str] = {self.id}
        self._owned: dict[str | None, bool] = {}

    def owns(self, subject: str | None) -> bool:
        """Whether this gateway serves ``subject`` with the members it knows."""
        owned = self._owned.get(subject)
        if owned is None:
            owned = self._owned[subject] = owner(self.members, subject) == self.id
        return owned

    def update(self, gateway_id: str, alive: bool) -> bool:
        """A member came (``alive``) or went; whether the members changed. This
        gateway stays a member of its own view whatever it is told."""
        if gateway_id == self.id:
            return False
        before = len(self.members)
        (self.members.add if alive else self.members.discard)(gateway_id)
        changed = len(self.members) != before
        if changed:
            self._owned.clear()
        return changed
