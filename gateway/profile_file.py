"""Moved to :mod:`bodynet.session.profile_file`, where clients may read it too.

Kept as a name only while branches written before the move still import it;
new code imports ``bodynet.session.profile_file``."""

from bodynet.session.profile_file import HEADER, load, save

__all__ = ["HEADER", "load", "save"]
