"""The zenoh bus: sessions and key expressions (``session``), ``--secure``'s mutual TLS
and access control (``security``) and its audit of what zenoh refuses (``audit``)."""
