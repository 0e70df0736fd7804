"""The low items of issue 51 (bad inputs): each refused with the words of what was wrong, the code a program
checks. ``set --verify-rounds -1`` (said "timeout_s must be positive"), ``scan`` with views = 1e9 (answered
``rejected``, a state's refusal, not ``invalid_params``)."""

import asyncio

import pytest

import phantom
from phantom.host.api import ApiError, ApiServer
from phantom.host.handlers import verify_of


def test_verify_rounds_out_of_range_is_refused_in_the_daemons_words_not_a_timeouts(tmp_path):
    """The client asks the daemon (whose set_target checks verify_rounds: host/handlers.verify_of) instead of
    failing first on the wait it computed from -1 rounds ("timeout_s must be a positive number")."""
    from phantom.host.client import AsyncPhantom, Connection

    async def set_target(params):
        verify_of(dict(params))
        return {}

    async def run():
        server = ApiServer(tmp_path / "d.sock", {"set_target": set_target})
        await server.start()
        try:
            client = AsyncPhantom(await Connection.open(tmp_path / "d.sock"))
            for rounds in (-1, 0):
                with pytest.raises(phantom.PhantomError, match="verify_rounds .*must be a whole number from 1") as no:
                    await client.set_volume(40.0, verify="scan", verify_rounds=rounds, wait=False)
                assert "timeout_s" not in str(no.value)
            await client.close()
        finally:
            await server.close()
    asyncio.run(run())


@pytest.mark.parametrize(("params", "words"), [
    ({"out": "x", "views": 10**9}, "views must be at most"),
    ({"out": "x", "views": 1e9}, "views must be a whole number"),
    ({"out": "x", "seed": -1}, "seed must be a whole number"),
    ({"out": "x", "elevations_deg": "0,30"}, "elevations_deg must be a list"),
    ({"out": "x", "colour": "red"}, "not colour"),
    ({"out": "x", "look": "nonsense"}, "look must be one of ideal, real .* got 'nonsense'"),
])
def test_a_scan_with_bad_params_is_invalid_params_not_rejected(tmp_path, params, words):
    from phantom.host.motion import Orbit, scan_method
    from phantom.scan.daemon_scan import DaemonScanner

    async def run():
        orbit = Orbit(lambda name, fields: None, lambda kind, text, level: None)
        scan = scan_method(orbit, DaemonScanner(), lambda: {"faults": [], "link": "online"})["scan"]
        with pytest.raises(ApiError, match=words) as refused:
            await scan({**params, "out": str(tmp_path / "capture")})
        assert refused.value.code == "invalid_params", refused.value
        assert not (tmp_path / "capture").exists()
    asyncio.run(run())
