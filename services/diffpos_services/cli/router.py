"""Zenoh router in this Python process (no zenohd binary needed)

Every diffpos service connects to one router as a Zenoh client; this command runs that
router inside Python (eclipse-zenoh in router mode), so a fresh machine needs nothing but
the pip install. Multicast scouting is off: clients must be given the endpoint explicitly.
In docker-compose the official eclipse/zenoh image (same 1.10.2 version) plays this role.

The router keeps no application state: it is ready when its listen port accepts
connections (clients started earlier simply wait for it, --connect-timeout-ms -1).

examples:
  diffpos router                                   listen on tcp/127.0.0.1:7447
  diffpos router --listen tcp/0.0.0.0:7447         accept connections from other hosts
                                                   (plain, unauthenticated: logged as an ERROR)
  diffpos anchor --connect tcp/127.0.0.1:7447 ...  (in another terminal)
  diffpos router --zenoh-config security/zenoh/router.json5
                                                   TLS + user/password + access control
                                                   (see security/README.md)

Stop with Ctrl-C or SIGTERM (the session is closed cleanly).
"""

from __future__ import annotations

import argparse
import logging

import zenoh

from diffpos_services.bus.session import add_zenoh_arguments, open_session, service_settings
from diffpos_services.errors import ConfigError
from diffpos_services.logs import add_logging_arguments, log_event, setup_logging
from diffpos_services.shutdown import Shutdown, run_main


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_zenoh_arguments(parser, mode="router")
    add_logging_arguments(parser)


def run(args: argparse.Namespace) -> int:
    log = setup_logging("router", level=args.log_level, fmt=args.log_format)

    def body() -> int:
        settings = service_settings(args, log)
        stop = Shutdown(log)
        try:
            session = open_session(settings, stop.event, logger=log)
        except zenoh.ZError as exc:
            raise ConfigError(
                f"the router cannot listen on {', '.join(settings.listen)}: "
                f"{str(exc).split(' at ')[0]} (port in use? certificate files readable?)"
            ) from None
        with session:
            log_event(log, logging.INFO, "router ready", listen=list(settings.listen), zid=str(session.zid()))
            stop.wait()
        log_event(log, logging.INFO, "router stopped")
        return 0

    return run_main(body, log)
