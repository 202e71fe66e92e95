"""Typed errors raised by the library; the CLI maps each to one stderr line and an exit code.

Exit codes (DESIGN.md section 8): 0 ok, 1 internal error, 2 usage/config, 3 device, 4 session/data.
"""

import errno

DISK_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS}


class MidasError(Exception):
    """Base class: the message says what was received, what was expected and what to do."""

    exit_code = 1


class ConfigError(MidasError):
    """A bad flag value, rig file or setting."""

    exit_code = 2


class DeviceError(MidasError):
    """A device could not be opened, stopped answering or spoke something unexpected."""

    exit_code = 3


class SessionError(MidasError):
    """A session folder or data file is missing, malformed or inconsistent."""

    exit_code = 4


class UnitsFailedError(MidasError):
    """Units of a batch run (one session, one fold...) failed; the others' results are kept."""

    exit_code = 4


def disk_full(exc: BaseException | None) -> OSError | None:
    """The OSError saying the disk is full, over quota or read-only, in ``exc`` or what it was raised from."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def disk_full_message(full: OSError) -> str:
    """``disk full / read-only: <path> (<reason>); free space and run again``."""
    return (f"disk full / read-only: {full.filename or 'the output folder'} "
            f"({full.strerror or errno.errorcode.get(full.errno or 0, full.errno)}); free space and run again")
