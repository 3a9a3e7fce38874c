"""The transport side of the master–robot protocol, shared by the master and the agent.

:mod:`transport.framing` cuts a byte stream into frames and frames the messages of
:mod:`minimize_surprise.wire`; :mod:`transport.stream` carries them over an asyncio stream;
:mod:`transport.tls` holds the optional TLS configuration of both sides. The codec itself stays in
the I/O-free :mod:`minimize_surprise` package.
"""
