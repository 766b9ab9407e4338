"""``armfusion deploy``: the command line of :mod:`armfusion.fusion.service.deploy` (a fleet's
certificates, credentials and Zenoh configs)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from armfusion.fusion.cli.common import console, emit_json, fail
from armfusion.fusion.cli.options import JsonOpt
from armfusion.fusion.service.deploy import CHAIR_NODES, INSTALL_DIR, DeployError, deploy


def register(app: typer.Typer) -> None:
    """Add the ``deploy`` command to ``app``."""

    @app.command("deploy")
    def deploy_command(
        fleet: Annotated[Path, typer.Option("--fleet", help="The fleet's folder: its CA, the base station's "
                                            "files, one folder per chair.")],
        chairs: Annotated[list[str] | None, typer.Argument(
            help="The chairs to write (each name is its certificate's CN and its key prefix); none: "
                 "only the base router's policy, from the chairs in the fleet.")] = None,
        base_address: Annotated[str | None, typer.Option(
            "--base-address", help="The base router's IP address (its certificate's subject alternative "
                                   "name, the chairs' connect endpoint; default: the fleet's, else "
                                   "127.0.0.1).")] = None,
        base_port: Annotated[int | None, typer.Option(
            "--base-port", help="The base router's TLS port (default: the fleet's, else 7448).")] = None,
        chair_port: Annotated[int, typer.Option(
            "--chair-port", help="The chair router's port on 127.0.0.1, for its nodes.")] = 7447,
        local: Annotated[bool, typer.Option(
            "--local", help="The configs name the files where they are written (all on this machine), "
                            "not /etc/armfusion.")] = False,
        force: Annotated[bool, typer.Option(
            "--force", help="Replace a chair's folder that exists (new certificate and passwords).")] = False,
        json_out: JsonOpt = False,
    ) -> None:
        """Write a fleet's certificates, credentials and Zenoh configs: each chair's (its
        certificate, its nodes' users and passwords, its router's and nodes' configs) and, the
        first time, the fleet's CA and the base station's; the base router's policy admits every
        chair of the fleet.

        To retire a chair, remove its folder and run deploy with no chair: the base router's
        policy then has no subject for its certificate, and denies whatever it sends."""
        try:
            report = deploy(fleet, list(chairs or ()), base_address=base_address, base_port=base_port,
                            chair_port=chair_port, local=local, force=force)
        except DeployError as e:
            fail(str(e))
        if json_out:
            emit_json(report.as_dict())
            return
        at = "" if local else f" (copy each folder to that machine's {INSTALL_DIR}/)"
        console.print(f"wrote {len(report.made)} files under {fleet}{at}", highlight=False)
        for c, folder in report.chairs.items():
            console.print(f"  {c}: {folder}/tls ({c}.pem, {c}.key), {folder}/zenoh (router.json5, "
                          f"{c}.users, {', '.join(f'{u}.json5' for u in CHAIR_NODES)})", highlight=False)
        console.print(f"  base router's policy admits {', '.join(report.fleet_chairs) or 'no chair'}: "
                      f"{fleet / 'base' / 'zenoh' / 'router.json5'} (restart the base router to apply it)",
                      highlight=False)
