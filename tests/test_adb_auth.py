"""Host key files in Android's format, the RSAPublicKey struct, and AUTH token signatures."""

from __future__ import annotations

import base64
import hashlib
import os
import stat
import struct
from pathlib import Path

import pytest

from drivers.adb.auth import (
    BLOB_SIZE,
    AdbKey,
    decode_public_blob,
    encode_public_blob,
    parse_public_key_text,
    verify_token_signature,
)
from drivers.adb.errors import KeyFileError

SHA1_DIGEST_INFO = bytes.fromhex("3021300906052b0e03021a05000414")


@pytest.fixture(scope="module")
def key() -> AdbKey:
    return AdbKey.generate("tester@rig")


def test_public_blob_layout(key: AdbKey) -> None:
    blob = key.public_blob()
    assert len(blob) == BLOB_SIZE == 524
    words, n0inv = struct.unpack_from("<II", blob)
    n = int.from_bytes(blob[8:264], "little")
    rr = int.from_bytes(blob[264:520], "little")
    (exponent,) = struct.unpack_from("<I", blob, 520)
    assert words == 64 and exponent == 65537
    assert n == key._private.public_key().public_numbers().n
    assert (n * n0inv) % 2**32 == 2**32 - 1  # n0inv = -1/n mod 2^32
    assert rr == pow(2, 4096, n)


def test_key_files_round_trip(tmp_path: Path, key: AdbKey) -> None:
    key.save(tmp_path)
    pub = (tmp_path / "adbkey.pub").read_text()
    assert pub.endswith(" tester@rig\n")
    assert base64.b64decode(pub.split(" ")[0]) == key.public_blob()
    assert (tmp_path / "adbkey").read_text().startswith("-----BEGIN PRIVATE KEY-----")
    assert stat.S_IMODE((tmp_path / "adbkey").stat().st_mode) == 0o600
    loaded = AdbKey.load(tmp_path)
    assert loaded.public_blob() == key.public_blob() and loaded.comment == "tester@rig"


def test_load_or_create_keeps_the_key(tmp_path: Path) -> None:
    first = AdbKey.load_or_create(tmp_path / "state")
    again = AdbKey.load_or_create(tmp_path / "state")
    assert first.public_blob() == again.public_blob()


def test_bad_key_files(tmp_path: Path) -> None:
    with pytest.raises(KeyFileError, match="cannot read"):
        AdbKey.load(tmp_path)
    (tmp_path / "adbkey").write_text("not a key")
    with pytest.raises(KeyFileError, match="not a PEM private key"):
        AdbKey.load(tmp_path)


def test_signature_is_pkcs1_over_token_as_sha1_digest(key: AdbKey) -> None:
    token = os.urandom(20)
    signature = key.sign(token)
    numbers = key._private.public_key().public_numbers()
    em = pow(int.from_bytes(signature, "big"), numbers.e, numbers.n).to_bytes(256, "big")
    t = SHA1_DIGEST_INFO + token  # the token is used as the digest itself, not hashed again
    assert em == b"\x00\x01" + b"\xff" * (256 - 3 - len(t)) + b"\x00" + t
    assert em[-20:] != hashlib.sha1(token).digest()


def test_verify_token_signature(key: AdbKey) -> None:
    token = os.urandom(20)
    signature = key.sign(token)
    assert verify_token_signature(key.public_blob(), token, signature)
    assert not verify_token_signature(key.public_blob(), os.urandom(20), signature)
    assert not verify_token_signature(AdbKey.generate().public_blob(), token, signature)
    assert not verify_token_signature(key.public_blob(), token[:19], signature)
    with pytest.raises(ValueError, match="5 bytes, not 20"):
        key.sign(b"short")


def test_public_key_text_round_trip_and_bad_blobs(key: AdbKey) -> None:
    assert parse_public_key_text(key.public_key_payload()) == key.public_blob()
    assert decode_public_blob(key.public_blob()).public_numbers() == key._private.public_key().public_numbers()
    assert encode_public_blob(decode_public_blob(key.public_blob())) == key.public_blob()
    with pytest.raises(ValueError, match="base64"):
        parse_public_key_text("!!!! user@host")
    bad = bytearray(key.public_blob())
    bad[4] ^= 1  # n0inv
    with pytest.raises(ValueError, match="n0inv"):
        decode_public_blob(bytes(bad))
    bad = bytearray(key.public_blob())
    bad[300] ^= 1  # rr
    with pytest.raises(ValueError, match="rr"):
        decode_public_blob(bytes(bad))
    with pytest.raises(ValueError, match="524"):
        decode_public_blob(bytes(100))
