"""The asyncio side of the master–robot protocol, shared by the master and the agent.

:mod:`transport.stream` carries the messages of :mod:`minimize_surprise.wire` over an asyncio
stream;
:mod:`transport.tls` holds the optional TLS configuration of both sides. The codec itself stays in
the I/O-free :mod:`minimize_surprise` package.
"""
