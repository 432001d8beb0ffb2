"""Running and training policies on a JetRacer over a serial motor controller (see docs/serial_protocol.md)."""
