"""The root of softplc's own errors.

Owns: SoftplcError. Every error softplc raises on purpose derives from it (alongside the
built-in kind it also is, such as ValueError or OSError), so `except SoftplcError` catches all
of them and none of Python's, and every one crosses processes whole (the compile process, the
channel): it pickles its class, its args and its attributes, whatever its __init__ takes.
Does not know: any particular error.
"""

from __future__ import annotations


class SoftplcError(Exception):
    """An error of softplc's own: a refused program, command, write, request or file."""

    def __reduce__(self) -> tuple[object, ...]:
        return _rebuilt, (type(self), self.args, dict(vars(self)))


def _rebuilt(cls: type[SoftplcError], args: tuple[object, ...],
             attributes: dict[str, object]) -> SoftplcError:
    """The error as it was, without calling its __init__ again (whose arguments may differ
    from the args it passed on)."""
    error = cls.__new__(cls, *args)
    error.args = args
    vars(error).update(attributes)
    return error
