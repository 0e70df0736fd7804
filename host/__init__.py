"""The host side: the daemon (asyncio link session, transports, control, scenes, Rerun logging, local API)
and the ``phantom`` command line."""
