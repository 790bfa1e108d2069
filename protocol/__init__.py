"""TPDEB's wire format: message types, the msgpack codec, validation and Zenoh key expressions.

Imports numpy and msgpack only; nothing here knows about torch, Zenoh sessions or files.
"""
