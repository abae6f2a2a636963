"""The firmware's velocity gains, set as its parameter system sets them.

On a Crazyflie, cflib's ``param.set_value("velCtlPid.vxKp", ...)`` writes the float the
firmware registered under that name (``PARAM_ADD(..., vxKp, &this.pidVX.pid.kp)`` in
``position_controller_pid.c``), and the velocity PID multiplies its next error by it. The
Python bindings compile that variable as a file-static struct (``this``) that SWIG does not
wrap, so this module finds it in the extension's ELF symbol table, places it in memory by an
exported function's address, and writes the same floats. It checks first that the floats
where the struct's layout puts them hold the firmware's stock gains (25 degrees per m/s, an
integral gain of 1, no derivative), and refuses otherwise: a build whose symbols are stripped
or whose layout differs keeps its stock gains, as a Crazyflie refuses an unknown parameter.
"""

from __future__ import annotations

import ctypes
import functools
import struct
import sys
from pathlib import Path
from types import ModuleType

SOURCE_FILE = "position_controller_pid.c"
STRUCT_NAME = "this"
ANCHOR_FUNCTION = "controllerPidInit"  # exported by the extension, placed by the loader
# struct pidAxis_s { PidObject pid; stab_mode_t previousMode; float setpoint; float output; }
# PidObject: 16 floats, lpf2pData (7 floats), bool -> 96 bytes; pidAxis_s -> 108 bytes.
AXIS_BYTES = 108
KP_OFFSET = 5 * 4  # desired, error, prevMeasured, integ, deriv, then kp, ki, kd
STOCK_GAINS = (25.0, 1.0, 0.0)  # PID_VEL_X_KP, _KI, _KD (and Y): degrees of tilt per m/s
AXES = ("vx", "vy")  # pidVX, pidVY: the struct's first two members

_SHT_SYMTAB = 2
_STT_OBJECT = 1
_STT_FILE = 4


class VelocityGains:
    """``velCtlPid.vxKp`` and ``vyKp`` (degrees of tilt per m/s of velocity error) in the
    loaded firmware: ``set(kp_deg)``, ``stock()`` puts back the firmware's 25."""

    def __init__(self, kp_addresses: tuple[int, ...]) -> None:
        self._floats = [ctypes.c_float.from_address(a) for a in kp_addresses]

    @classmethod
    def find(cls, fw: ModuleType) -> VelocityGains | None:
        """The gains in ``fw``'s extension, or None where they cannot be found for sure."""
        extension = getattr(fw, "_cffirmware", None) or sys.modules.get("_cffirmware")
        path = getattr(extension, "__file__", None)
        if path is None:
            return None
        offsets = _struct_after_anchor(path)
        try:
            library = ctypes.CDLL(path)
            loaded = ctypes.cast(getattr(library, ANCHOR_FUNCTION), ctypes.c_void_p).value
        except (OSError, AttributeError):
            return None
        if offsets is None or loaded is None:
            return None
        base = loaded + offsets
        kp_addresses = tuple(base + i * AXIS_BYTES + KP_OFFSET for i in range(len(AXES)))
        for address in kp_addresses:
            gains = (ctypes.c_float * 3).from_address(address)
            if tuple(float(g) for g in gains) != STOCK_GAINS and not _set_by_us(gains):
                return None
        return cls(kp_addresses)

    def set(self, kp_deg: float) -> None:
        for f in self._floats:
            f.value = kp_deg

    def stock(self) -> None:
        self.set(STOCK_GAINS[0])

    def kp_deg(self) -> tuple[float, ...]:
        return tuple(f.value for f in self._floats)


@functools.cache
def _struct_after_anchor(path: str) -> int | None:
    """How far the struct lies past the exported function, by the file's symbol table."""
    try:
        table = _symbols(Path(path).read_bytes())
    except (OSError, ValueError, struct.error):
        return None
    symbols = _static_objects(table, SOURCE_FILE)
    anchor = _global_symbol(table, ANCHOR_FUNCTION)
    if STRUCT_NAME not in symbols or anchor is None:
        return None
    return symbols[STRUCT_NAME] - anchor


def _set_by_us(gains: ctypes.Array[ctypes.c_float]) -> bool:
    """An earlier vehicle in this process may have left its own kp: ki and kd still stock."""
    return (float(gains[1]), float(gains[2])) == STOCK_GAINS[1:] and 0.0 < float(gains[0]) < 90.0


def _sections(elf: bytes) -> list[tuple[int, int, int, int, int]]:
    """(type, offset, size, link, entry size) of each section of a little-endian ELF64."""
    if elf[:4] != b"\x7fELF" or elf[4] != 2 or elf[5] != 1:
        raise ValueError("not a little-endian ELF64 file")
    shoff = struct.unpack_from("<Q", elf, 0x28)[0]
    shentsize, shnum = struct.unpack_from("<HH", elf, 0x3A)
    out = []
    for i in range(shnum):
        _name, kind, _flags, _addr, offset, size, link, _info, _align, entsize = struct.unpack_from(
            "<IIQQQQIIQQ", elf, shoff + i * shentsize
        )
        out.append((kind, offset, size, link, entsize))
    return out


def _symbols(elf: bytes) -> list[tuple[str, int, int]]:
    """(name, type, value) of each entry of the full symbol table, in its order."""
    sections = _sections(elf)
    table = next((s for s in sections if s[0] == _SHT_SYMTAB), None)
    if table is None:
        raise ValueError("no symbol table (the extension is stripped)")
    _kind, offset, size, link, entsize = table
    strings_offset = sections[link][1]
    out = []
    for at in range(offset, offset + size, entsize):
        name_at, info, _other, _shndx, value, _size = struct.unpack_from("<IBBHQQ", elf, at)
        end = elf.index(b"\0", strings_offset + name_at)
        out.append((elf[strings_offset + name_at : end].decode(), info & 0xF, value))
    return out


def _static_objects(table: list[tuple[str, int, int]], source_file: str) -> dict[str, int]:
    """The file-static data objects of one source file in the symbol table: the local
    symbols that follow its FILE entry."""
    objects: dict[str, int] = {}
    current = ""
    for name, kind, value in table:
        if kind == _STT_FILE:
            current = name
        elif kind == _STT_OBJECT and Path(current).name == source_file:
            objects.setdefault(name, value)
    return objects


def _global_symbol(table: list[tuple[str, int, int]], name: str) -> int | None:
    values = [value for n, _kind, value in table if n == name and value]
    return values[0] if values else None
