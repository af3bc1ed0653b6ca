"""The GID rmw_zenoh gives an entity: XXH3-128 of its liveliness token (keys.py), in 16 bytes.

rmw_zenoh_cpp hashes the token's text with XXH3's 128-bit variant, seed 0 and the default secret
(simplified_xxhash3.cpp, a reduction of xxHash 0.8's XXH3_128bits), and copies the result's low 64 bits then its
high 64 bits, each in the machine's order, little-endian on every platform ROS 2 supports (liveliness_utils.cpp
Entity::Entity). The GID goes into every sample's attachment (attachment.py) and is what ``ros2 topic info -v``
shows. This is XXH3-128 written out in Python from that algorithm; tests/protocol/ros2/fixtures/fixtures.json
holds the ``xxhash`` package's values for every length class of the algorithm to check it against.
"""
from __future__ import annotations

_MASK = (1 << 64) - 1
_PRIME32_1, _PRIME32_2, _PRIME32_3 = 0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D
_PRIME64_1, _PRIME64_2, _PRIME64_3 = 0x9E3779B185EBCA87, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9
_PRIME64_4, _PRIME64_5 = 0x85EBCA77C2B2AE63, 0x27D4EB2F165667C5
_PRIME_MX1, _PRIME_MX2 = 0x165667919E3779F9, 0x9FB21C651E98DF25
#: XXH3's default secret, 192 bytes (xxhash.h XXH3_kSecret)
_SECRET = bytes.fromhex(
    "b8fe6c3923a44bbe7c01812cf721ad1cded46de9839097db7240a4a4b7b3671fcb79e64eccc0e578825ad07dccff7221"
    "b8084674f743248ee03590e6813a264c3c2852bb91c300cb88d0658b1b532ea371644897a20df94e3819ef46a9deacd8"
    "a8fa763fe39c343ff9dcbbc7c70b4f1d8a51e04bcdb45931c89f7ec9d9787364eac5ac8334d3ebc3c581a0fffa1363eb"
    "170ddd51b7f0da49d316552629d4689e2b16be587d47a1fc8ff8b8d17ad031ce45cb3a8f95160428afd7fbcabb4b407e")
_STRIPE = 64           # bytes per stripe of the long path
_SECRET_STEP = 8       # secret bytes advanced per stripe
_LAST_ACC_START = 7    # the last stripe's secret offset back from the end
_MERGE_ACCS_START = 11
_MIDSIZE_START, _MIDSIZE_LAST = 3, 17
_SECRET_SIZE_MIN = 136


def _u64(data: bytes, offset: int) -> int:
    return int.from_bytes(data[offset:offset + 8], "little")


def _u32(data: bytes, offset: int) -> int:
    return int.from_bytes(data[offset:offset + 4], "little")


def _mul128(a: int, b: int) -> tuple[int, int]:
    product = a * b
    return product & _MASK, product >> 64


def _fold(a: int, b: int) -> int:
    low, high = _mul128(a, b)
    return low ^ high


def _avalanche(h: int) -> int:
    h ^= h >> 37
    h = (h * _PRIME_MX1) & _MASK
    return h ^ (h >> 32)


def _xxh64_avalanche(h: int) -> int:
    h ^= h >> 33
    h = (h * _PRIME64_2) & _MASK
    h ^= h >> 29
    h = (h * _PRIME64_3) & _MASK
    return h ^ (h >> 32)


def _len_0_to_16(data: bytes) -> tuple[int, int]:
    size = len(data)
    if size > 8:
        flip_low = _u64(_SECRET, 32) ^ _u64(_SECRET, 40)
        flip_high = _u64(_SECRET, 48) ^ _u64(_SECRET, 56)
        low_input, high_input = _u64(data, 0), _u64(data, size - 8)
        low, high = _mul128(low_input ^ high_input ^ flip_low, _PRIME64_1)
        low = (low + ((size - 1) << 54)) & _MASK
        high_input ^= flip_high
        high = (high + high_input + (high_input & 0xFFFFFFFF) * (_PRIME32_2 - 1)) & _MASK
        low ^= int.from_bytes(high.to_bytes(8, "little"), "big")  # byte swap
        out_low, out_high = _mul128(low, _PRIME64_2)
        out_high = (out_high + high * _PRIME64_2) & _MASK
        return _avalanche(out_low), _avalanche(out_high)
    if size >= 4:
        combined = _u32(data, 0) + (_u32(data, size - 4) << 32)
        keyed = combined ^ (_u64(_SECRET, 16) ^ _u64(_SECRET, 24))
        low, high = _mul128(keyed, (_PRIME64_1 + (size << 2)) & _MASK)
        high = (high + (low << 1)) & _MASK
        low ^= high >> 3
        low ^= low >> 35
        low = (low * _PRIME_MX2) & _MASK
        low ^= low >> 28
        return low, _avalanche(high)
    if size:
        combined_low = (data[0] << 16) | (data[size >> 1] << 24) | data[size - 1] | (size << 8)
        swapped = int.from_bytes(combined_low.to_bytes(4, "little"), "big")
        combined_high = ((swapped << 13) | (swapped >> 19)) & 0xFFFFFFFF
        keyed_low = combined_low ^ (_u32(_SECRET, 0) ^ _u32(_SECRET, 4))
        keyed_high = combined_high ^ (_u32(_SECRET, 8) ^ _u32(_SECRET, 12))
        return _xxh64_avalanche(keyed_low), _xxh64_avalanche(keyed_high)
    return (_xxh64_avalanche(_u64(_SECRET, 64) ^ _u64(_SECRET, 72)),
            _xxh64_avalanche(_u64(_SECRET, 80) ^ _u64(_SECRET, 88)))


def _mix16(data: bytes, offset: int, secret_offset: int) -> int:
    return _fold(_u64(data, offset) ^ _u64(_SECRET, secret_offset),
                 _u64(data, offset + 8) ^ _u64(_SECRET, secret_offset + 8))


def _mix32(acc: tuple[int, int], data: bytes, first: int, second: int, secret_offset: int) -> tuple[int, int]:
    low, high = acc
    low = (low + _mix16(data, first, secret_offset)) & _MASK
    low ^= (_u64(data, second) + _u64(data, second + 8)) & _MASK
    high = (high + _mix16(data, second, secret_offset + 16)) & _MASK
    high ^= (_u64(data, first) + _u64(data, first + 8)) & _MASK
    return low, high


def _finish_mid(acc: tuple[int, int], size: int) -> tuple[int, int]:
    low, high = acc
    out_low = (low + high) & _MASK
    out_high = (low * _PRIME64_1 + high * _PRIME64_4 + size * _PRIME64_2) & _MASK
    return _avalanche(out_low), (-_avalanche(out_high)) & _MASK


def _len_17_to_128(data: bytes) -> tuple[int, int]:
    size = len(data)
    acc = ((size * _PRIME64_1) & _MASK, 0)
    # pairs from the outside in, the outermost last: 96 < size, 64 < size, 32 < size, always
    for threshold, front, secret_offset in ((96, 48, 96), (64, 32, 64), (32, 16, 32)):
        if size > threshold:
            acc = _mix32(acc, data, front, size - front - 16, secret_offset)
    return _finish_mid(_mix32(acc, data, 0, size - 16, 0), size)


def _len_129_to_240(data: bytes) -> tuple[int, int]:
    size = len(data)
    acc = ((size * _PRIME64_1) & _MASK, 0)
    for end in range(32, 160, 32):
        acc = _mix32(acc, data, end - 32, end - 16, end - 32)
    acc = (_avalanche(acc[0]), _avalanche(acc[1]))
    for end in range(160, size + 1, 32):  # ``<=``: a length divisible by 32 mixes its last 32 bytes twice
        acc = _mix32(acc, data, end - 32, end - 16, _MIDSIZE_START + end - 160)
    acc = _mix32(acc, data, size - 16, size - 32, _SECRET_SIZE_MIN - _MIDSIZE_LAST - 16)
    return _finish_mid(acc, size)


def _accumulate_stripe(acc: list[int], data: bytes, offset: int, secret_offset: int) -> None:
    for lane in range(8):
        value = _u64(data, offset + 8 * lane)
        keyed = value ^ _u64(_SECRET, secret_offset + 8 * lane)
        acc[lane ^ 1] = (acc[lane ^ 1] + value) & _MASK
        acc[lane] = (acc[lane] + (keyed & 0xFFFFFFFF) * (keyed >> 32)) & _MASK


def _scramble(acc: list[int]) -> None:
    secret_offset = len(_SECRET) - _STRIPE
    for lane in range(8):
        value = acc[lane] ^ (acc[lane] >> 47) ^ _u64(_SECRET, secret_offset + 8 * lane)
        acc[lane] = (value * _PRIME32_1) & _MASK


def _merge(acc: list[int], secret_offset: int, start: int) -> int:
    result = start
    for pair in range(4):
        result += _fold(acc[2 * pair] ^ _u64(_SECRET, secret_offset + 16 * pair),
                        acc[2 * pair + 1] ^ _u64(_SECRET, secret_offset + 16 * pair + 8))
    return _avalanche(result & _MASK)


def _long(data: bytes) -> tuple[int, int]:
    size = len(data)
    acc = [_PRIME32_3, _PRIME64_1, _PRIME64_2, _PRIME64_3, _PRIME64_4, _PRIME32_2, _PRIME64_5, _PRIME32_1]
    stripes_per_block = (len(_SECRET) - _STRIPE) // _SECRET_STEP
    block = _STRIPE * stripes_per_block
    blocks = (size - 1) // block
    for number in range(blocks):
        for stripe in range(stripes_per_block):
            _accumulate_stripe(acc, data, number * block + stripe * _STRIPE, stripe * _SECRET_STEP)
        _scramble(acc)
    for stripe in range(((size - 1) - block * blocks) // _STRIPE):
        _accumulate_stripe(acc, data, blocks * block + stripe * _STRIPE, stripe * _SECRET_STEP)
    _accumulate_stripe(acc, data, size - _STRIPE, len(_SECRET) - _STRIPE - _LAST_ACC_START)
    low = _merge(acc, _MERGE_ACCS_START, (size * _PRIME64_1) & _MASK)
    high = _merge(acc, len(_SECRET) - 64 - _MERGE_ACCS_START, ~(size * _PRIME64_2) & _MASK)
    return low, high


def xxh3_128(data: bytes) -> tuple[int, int]:
    """XXH3's 128-bit hash of ``data`` (seed 0, default secret) as (low 64 bits, high 64 bits)."""
    if len(data) <= 16:
        return _len_0_to_16(data)
    if len(data) <= 128:
        return _len_17_to_128(data)
    if len(data) <= 240:
        return _len_129_to_240(data)
    return _long(data)


def entity_gid(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh derives from an entity's liveliness token: low then high half, little-endian."""
    low, high = xxh3_128(token.encode("utf-8"))
    return low.to_bytes(8, "little") + high.to_bytes(8, "little")
