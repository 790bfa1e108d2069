"""Zenoh plumbing: sessions, security (TLS, passwords, access control), certificates and the
conversions between messages and the core's types."""
