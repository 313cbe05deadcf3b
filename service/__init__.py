"""The falcon-plan Zenoh service: key layout, JSON codec and schemas, request handling,
the server, a client and the ``serve`` entry point (see service/README.md).

Nothing here imports zenoh at package import; the modules that need it import it lazily.
"""
