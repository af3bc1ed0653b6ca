"""The mfvs wire contract: key expressions, message types, conventions, Kinova API types, RS-485 codec.

Nothing here opens a zenoh session; everything here is importable by any client (docs/contracts.md).
"""
