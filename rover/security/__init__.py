"""Mutual TLS between hosts and access control generated from the wiring (docs/security.md)."""
