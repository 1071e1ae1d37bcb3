"""Errors raised when a message cannot be encoded, decoded or validated.

Every error names the field at fault and what was wrong, and carries a short machine-readable
`reason` so a subscriber can count rejected messages per cause without parsing text.
"""

from __future__ import annotations


class ProtocolError(ValueError):
    """Base of every wire-protocol error. `field` is a dotted path ("obs", "arrays.reward")."""

    reason = "protocol"

    def __init__(self, message: str, field: str | None = None) -> None:
        self.field = field
        super().__init__(f"{field}: {message}" if field else message)


class SizeError(ProtocolError):
    """The payload is larger than the size cap for its message type."""

    reason = "size"


class DecodeError(ProtocolError):
    """The bytes are not well-formed msgpack, or not a map with string keys."""

    reason = "decode"


class VersionError(ProtocolError):
    """The message's schema version `v` is not the one this code speaks."""

    reason = "version"


class TypeTagError(ProtocolError):
    """The type tag is unknown, or not one of the types the receiver expects."""

    reason = "type"


class FieldError(ProtocolError):
    """A field is missing, unknown, of the wrong type, or out of its allowed values."""

    reason = "field"


class DTypeError(ProtocolError):
    """An array has a dtype outside the whitelist or not the one the field requires."""

    reason = "dtype"


class ShapeError(ProtocolError):
    """An array's shape disagrees with its byte count, the other fields or the declared Dims."""

    reason = "shape"


class NonFiniteError(ProtocolError):
    """A float array or float field holds NaN or +-inf."""

    reason = "nonfinite"


class RangeError(ProtocolError):
    """Values lie outside their allowed range (messages outside [-1, 1], action ids >= n)."""

    reason = "range"


class ChecksumError(ProtocolError):
    """A weights blob does not match its sha256."""

    reason = "checksum"


class KeyMismatchError(ProtocolError):
    """The payload names another agent, role or sender than the key it came on (protocol/binding.py)."""

    reason = "key_mismatch"
