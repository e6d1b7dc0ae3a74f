"""The ADB host key and AUTH signatures, in Android's own formats.

``adbkey`` holds the RSA-2048 private key (PEM, PKCS#8) and ``adbkey.pub`` the public key as
Android's ``RSAPublicKey`` struct, base64-encoded, followed by `` user@host``. The struct (524
bytes, little-endian words): modulus size in 32-bit words (64), n0inv = -1/n mod 2**32, the
modulus (256 bytes LE), rr = (2**2048)**2 mod n (256 bytes LE), public exponent.

AUTH TOKEN signing is PKCS#1 v1.5 over the 20-byte token treated as an already-hashed SHA-1
digest; adbd verifies it with the same struct (drivers/sim/phone.py does too).
"""

from __future__ import annotations

import base64
import getpass
import os
import socket
import struct
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import padding, rsa
from cryptography.hazmat.primitives.asymmetric.utils import Prehashed

from drivers.adb.errors import KeyFileError

KEY_BITS = 2048
KEY_WORDS = KEY_BITS // 32
KEY_BYTES = KEY_BITS // 8
EXPONENT = 65537
BLOB_SIZE = 4 + 4 + KEY_BYTES + KEY_BYTES + 4
TOKEN_SIZE = 20
_BLOB = struct.Struct(f"<II{KEY_BYTES}s{KEY_BYTES}sI")


def encode_public_blob(key: rsa.RSAPublicKey) -> bytes:
    """Android's RSAPublicKey struct (524 bytes) for an RSA-2048 public key."""
    numbers = key.public_numbers()
    n, e = numbers.n, numbers.e
    if n.bit_length() != KEY_BITS:
        raise ValueError(f"ADB keys are RSA-{KEY_BITS}; this one has {n.bit_length()} bits")
    n0inv = (-pow(n, -1, 1 << 32)) % (1 << 32)
    rr = pow(1 << KEY_BITS, 2, n)
    return _BLOB.pack(KEY_WORDS, n0inv, n.to_bytes(KEY_BYTES, "little"),
                      rr.to_bytes(KEY_BYTES, "little"), e)


def decode_public_blob(blob: bytes) -> rsa.RSAPublicKey:
    """The RSA public key in an Android RSAPublicKey struct; ValueError if the struct is inconsistent."""
    if len(blob) != BLOB_SIZE:
        raise ValueError(f"RSAPublicKey blob is {len(blob)} bytes, not {BLOB_SIZE}")
    words, n0inv, modulus, rr, exponent = _BLOB.unpack(blob)
    if words != KEY_WORDS:
        raise ValueError(f"modulus size {words} words, not {KEY_WORDS}")
    n = int.from_bytes(modulus, "little")
    if n.bit_length() != KEY_BITS or n % 2 == 0:
        raise ValueError("modulus is not an odd 2048-bit number")
    if (n0inv * n + 1) % (1 << 32) != 0:
        raise ValueError("n0inv does not match the modulus")
    if int.from_bytes(rr, "little") != pow(1 << KEY_BITS, 2, n):
        raise ValueError("rr does not match the modulus")
    return rsa.RSAPublicNumbers(exponent, n).public_key()


def parse_public_key_text(text: str | bytes) -> bytes:
    """The struct from adbkey.pub text or an AUTH RSAPUBLICKEY payload ('base64 user@host\\0')."""
    if isinstance(text, bytes):
        text = text.rstrip(b"\0").decode("ascii", "replace")
    encoded = text.strip().split(" ", 1)[0]
    try:
        blob = base64.b64decode(encoded, validate=True)
    except ValueError as exc:
        raise ValueError(f"public key is not base64: {exc}") from None
    decode_public_blob(blob)
    return blob


def verify_token_signature(blob: bytes, token: bytes, signature: bytes) -> bool:
    """True when signature is the PKCS#1 v1.5 signature of token (as a SHA-1 digest) by blob's key."""
    if len(token) != TOKEN_SIZE:
        return False
    try:
        decode_public_blob(blob).verify(signature, token, padding.PKCS1v15(), Prehashed(hashes.SHA1()))
    except (InvalidSignature, ValueError):
        return False
    return True


def _default_comment() -> str:
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = "tbp"
    return f"{user}@{socket.gethostname()}"


class AdbKey:
    """An ADB host key pair: signs AUTH tokens and gives the public key blob the phone stores."""

    PRIVATE_NAME = "adbkey"
    PUBLIC_NAME = "adbkey.pub"

    def __init__(self, private_key: rsa.RSAPrivateKey, comment: str | None = None) -> None:
        if private_key.key_size != KEY_BITS:
            raise KeyFileError("host", "key", f"ADB keys are RSA-{KEY_BITS}, not {private_key.key_size}")
        self._private = private_key
        self.comment = comment or _default_comment()

    @classmethod
    def generate(cls, comment: str | None = None) -> AdbKey:
        """A fresh RSA-2048 key (exponent 65537), kept in memory only."""
        return cls(rsa.generate_private_key(public_exponent=EXPONENT, key_size=KEY_BITS), comment)

    @classmethod
    def load(cls, state_dir: Path) -> AdbKey:
        """Read adbkey (PEM) from state_dir; the comment comes from adbkey.pub when present."""
        path = Path(state_dir) / cls.PRIVATE_NAME
        try:
            private = serialization.load_pem_private_key(path.read_bytes(), password=None)
        except OSError as exc:
            raise KeyFileError(str(path), "load", f"cannot read: {exc.strerror}") from exc
        except (ValueError, TypeError) as exc:
            raise KeyFileError(str(path), "load", f"not a PEM private key: {exc}") from exc
        if not isinstance(private, rsa.RSAPrivateKey):
            raise KeyFileError(str(path), "load", f"not an RSA key: {type(private).__name__}")
        comment = None
        pub = path.with_name(cls.PUBLIC_NAME)
        if pub.exists():
            parts = pub.read_text(errors="replace").strip().split(" ", 1)
            comment = parts[1] if len(parts) == 2 else None
        return cls(private, comment)

    @classmethod
    def load_or_create(cls, state_dir: Path, comment: str | None = None) -> AdbKey:
        """The key in state_dir, created there (mode 0600) on first use."""
        state_dir = Path(state_dir)
        if (state_dir / cls.PRIVATE_NAME).exists():
            return cls.load(state_dir)
        key = cls.generate(comment)
        key.save(state_dir)
        return key

    def save(self, state_dir: Path) -> None:
        """Write adbkey (0600) and adbkey.pub, each atomically."""
        state_dir = Path(state_dir)
        state_dir.mkdir(parents=True, exist_ok=True)
        pem = self._private.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                          serialization.NoEncryption())
        _write_atomic(state_dir / self.PRIVATE_NAME, pem, 0o600)
        _write_atomic(state_dir / self.PUBLIC_NAME, self.public_key_text().encode() + b"\n", 0o644)

    def public_blob(self) -> bytes:
        """Android's RSAPublicKey struct of this key (524 bytes)."""
        return encode_public_blob(self._private.public_key())

    def public_key_text(self) -> str:
        """adbkey.pub content without newline: 'base64(struct) user@host'."""
        return base64.b64encode(self.public_blob()).decode("ascii") + " " + self.comment

    def public_key_payload(self) -> bytes:
        """The AUTH RSAPUBLICKEY payload: the adbkey.pub text and a NUL."""
        return self.public_key_text().encode("ascii") + b"\0"

    def sign(self, token: bytes) -> bytes:
        """AUTH SIGNATURE payload: PKCS#1 v1.5 signature of the 20-byte token as a SHA-1 digest."""
        if len(token) != TOKEN_SIZE:
            raise ValueError(f"AUTH token is {len(token)} bytes, not {TOKEN_SIZE}")
        return self._private.sign(token, padding.PKCS1v15(), Prehashed(hashes.SHA1()))


def _write_atomic(path: Path, data: bytes, mode: int) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
