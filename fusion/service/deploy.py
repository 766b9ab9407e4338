"""``armfusion deploy``: a fleet's certificates, credentials and Zenoh configs, from the
templates of ``config/deploy/``.

One command per chair (or several at once) writes, under the fleet folder ``FLEET``::

    FLEET/ca/        ca.key ca.pem                 the fleet's CA: stays with the operator
    FLEET/base/tls/  ca.pem router.key router.pem base.key base.pem
    FLEET/base/zenoh/router.json5                  the base router: every chair in FLEET
    FLEET/base/zenoh/base.json5                    a base-station node (monitor, recalibrate)
    FLEET/<chair>/tls/   ca.pem <chair>.key <chair>.pem
    FLEET/<chair>/zenoh/ router.json5              the chair's router (chair.json5)
    FLEET/<chair>/zenoh/ <chair>.users             its user dictionary, one user:password a node
    FLEET/<chair>/zenoh/ drivers.json5 serve.json5 record.json5 monitor.json5   (node.json5)

The CA and the base station's certificates are made once, the first time; the base router's
config is written again on every run, with a rule, a subject and a policy for every chair
that has a certificate in ``FLEET`` (restart the base router to apply it): a chair whose
folder was removed is no longer admitted (its certificate still passes the TLS handshake, and
the policy, default deny, drops everything it sends); with no chair, a run writes only that
config (and, in a new fleet, the CA and the base station's files). A chair's folder that
exists is refused (its certificate and passwords would change) unless ``force``. Later runs
take the base router's address and port from the base station's files, and refuse others
(its certificate names that address).
Certificates: P-256, made by the ``openssl`` command line as docs/service-deploy.md's recipe,
CN = the node's name, the base router's subject alternative name its address (a client that
verifies the name, ``verify_name_on_connect``, accepts it only then). Passwords: 24 random
characters each (:func:`secrets.token_urlsafe`). Keys, passwords and the node configs that
hold them are mode 0600, their folders 0700.

The configs name their files where they will be on each machine (``/etc/armfusion/tls/``,
``/etc/armfusion/zenoh/``: copy ``FLEET/<chair>/`` to the chair's ``/etc/armfusion/``), or,
with ``local``, where they are written (one machine, as the tests).
"""

from __future__ import annotations

import ipaddress
import json
import re
import secrets
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from armfusion.fusion.service.payloads import check_name
from armfusion.fusion.service.zenoh_config import DEPLOY_CONFIG_DIR

INSTALL_DIR = "/etc/armfusion"
"""Where a machine's files go: ``tls/`` and ``zenoh/`` below it (the templates' paths)."""
CHAIR_NODES = ("drivers", "serve", "record", "monitor")
"""A chair's nodes, one user each; ``drivers`` alone may publish raw samples (chair.json5)."""
BASE_NAMES = ("ca", "base", "router")
"""Names a chair cannot take: the fleet's CA and the base station's own folders and CNs."""
CERT_DAYS = 825
CA_DAYS = 3650
PLACEHOLDER_PASSWORD = "CHANGE-ME"


class DeployError(RuntimeError):
    """A fleet cannot be written as asked (a bad name or address, a folder that exists, no openssl)."""


@dataclass
class DeployReport:
    fleet: Path
    chairs: dict[str, Path] = field(default_factory=dict)
    """The chairs written now, and their folders."""
    fleet_chairs: tuple[str, ...] = ()
    """Every chair the base router's policy now admits."""
    made: list[str] = field(default_factory=list)
    """Files written, relative to ``fleet``."""

    def as_dict(self) -> dict:
        return {"fleet": str(self.fleet), "chairs": {k: str(v) for k, v in self.chairs.items()},
                "base_router_admits": list(self.fleet_chairs), "written": self.made}


def _openssl(*args: str, cwd: Path) -> None:
    if shutil.which("openssl") is None:
        raise DeployError("armfusion deploy makes the certificates with the openssl command: install it "
                          "(e.g. apt install openssl)")
    r = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True, timeout=60)
    if r.returncode != 0:
        raise DeployError(f"openssl {args[0]} failed in {cwd}: {r.stderr.strip()[-400:]}")


def _private(path: Path) -> None:
    path.chmod(0o600)


def _folder(path: Path) -> Path:
    """``path``, made (mode 0700) if it is not there; one that is keeps its mode."""
    if not path.is_dir():
        path.mkdir(parents=True)
        path.chmod(0o700)
    return path


def make_ca(ca_dir: Path) -> None:
    """The fleet's CA (``ca.key`` 0600, ``ca.pem``) in ``ca_dir``."""
    _folder(ca_dir)
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
             "-keyout", "ca.key", "-out", "ca.pem", "-days", str(CA_DAYS),
             "-subj", "/CN=armfusion fleet CA", "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=ca_dir)
    _private(ca_dir / "ca.key")


def make_certificate(ca_dir: Path, tls_dir: Path, name: str, alt_names: str) -> None:
    """``name.key`` (0600) and ``name.pem`` in ``tls_dir``: CN=name, valid as server and
    client, ``alt_names`` its subject alternative names (e.g. ``IP:127.0.0.1``), signed by
    the CA of ``ca_dir``, whose certificate is copied beside it as ``ca.pem``."""
    _folder(tls_dir)
    (tls_dir / f"{name}.ext").write_text("basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n"
                                         f"extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName={alt_names}\n")
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
             "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=tls_dir)
    _private(tls_dir / f"{name}.key")
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", str((ca_dir / "ca.pem").resolve()),
             "-CAkey", str((ca_dir / "ca.key").resolve()), "-CAcreateserial", "-out", f"{name}.pem",
             "-days", str(CERT_DAYS), "-extfile", f"{name}.ext", cwd=tls_dir)
    for leftover in (f"{name}.ext", f"{name}.csr"):
        (tls_dir / leftover).unlink()
    shutil.copyfile(ca_dir / "ca.pem", tls_dir / "ca.pem")


def _substitute(text: str, template: str, replacements: dict[str, str]) -> str:
    """``text`` with each key replaced; a key the template lacks is an error (the template
    changed under the code), not a silent no-op."""
    for old, new in replacements.items():
        if old not in text:
            raise DeployError(f"config/deploy/{template}: expected {old!r} in the template")
        text = text.replace(old, new)
    return text


def _write(path: Path, text: str, private: bool = False) -> None:
    path.write_text(text, encoding="utf-8")
    if private:
        _private(path)


def _installed(folder: Path, local: bool) -> str:
    return str(folder.resolve()) if local else INSTALL_DIR


def _chair_files(fleet: Path, chair: str, base_endpoint: str, chair_endpoint: str, local: bool) -> list[Path]:
    """A chair's certificate, user dictionary, router config and node configs."""
    folder = _folder(fleet / chair)
    make_certificate(fleet / "ca", folder / "tls", chair, f"DNS:{chair}")
    zdir = _folder(folder / "zenoh")
    at = _installed(folder, local)
    passwords = {u: secrets.token_urlsafe(18) for u in CHAIR_NODES}
    _write(zdir / f"{chair}.users", "".join(f"{u}:{p}\n" for u, p in passwords.items()), private=True)
    router = (DEPLOY_CONFIG_DIR / "chair.json5").read_text(encoding="utf-8")
    router = _substitute(router, "chair.json5", {  # the name first: a local path may hold "chair1"
        "chair1": chair, '"/etc/armfusion/tls/': f'"{at}/tls/', '"/etc/armfusion/zenoh/': f'"{at}/zenoh/',
        '"tcp/127.0.0.1:7447"': json.dumps(chair_endpoint),
        '"tls/127.0.0.1:7448"': json.dumps(base_endpoint)})
    _write(zdir / "router.json5", router)
    node = (DEPLOY_CONFIG_DIR / "node.json5").read_text(encoding="utf-8")
    for user, password in passwords.items():
        text = _substitute(node, "node.json5", {
            'user: "drivers"': f"user: {json.dumps(user)}",
            f'password: "{PLACEHOLDER_PASSWORD}"': f"password: {json.dumps(password)}",
            '"tcp/127.0.0.1:7447"': json.dumps(chair_endpoint)})
        _write(zdir / f"{user}.json5", text, private=True)
    return [*(folder / "tls").iterdir(), *zdir.iterdir()]


def _base_router(fleet: Path, chairs: tuple[str, ...], base_endpoint: str, local: bool) -> str:
    """config/deploy/router.json5 with the base's paths and endpoint, and its policy's
    per-chair rule, subject and policy (the template's chair1) once for each of ``chairs``."""
    import zenoh

    template = DEPLOY_CONFIG_DIR / "router.json5"
    acl = json.loads(zenoh.Config.from_file(str(template)).get_json("access_control"))
    own = re.compile(r"^(chair\d+) sends its own$")
    template_chairs = {m.group(1) for r in acl["rules"] if (m := own.match(r["id"]))}
    if "chair1" not in template_chairs:
        raise DeployError(f"{template}: expected the rule 'chair1 sends its own'")
    rule = next(r for r in acl["rules"] if r["id"] == "chair1 sends its own")
    policy = next(p for p in acl["policies"] if p["id"] == "chair1")
    acl["rules"] = [r for r in acl["rules"] if not own.match(r["id"])] + [
        {**rule, "id": f"{c} sends its own", "key_exprs": [f"armfusion/{c}/**"]} for c in chairs]
    acl["subjects"] = [s for s in acl["subjects"] if s["id"] not in template_chairs] + [
        {"id": c, "cert_common_names": [c]} for c in chairs]
    acl["policies"] = [p for p in acl["policies"] if p["id"] not in template_chairs] + [
        {**policy, "id": c, "subjects": [c],
         "rules": [f"{c} sends its own" if r == "chair1 sends its own" else r for r in policy["rules"]]}
        for c in chairs]
    text = template.read_text(encoding="utf-8")
    head, sep, _ = text.partition("\n  access_control: {")
    if not sep:
        raise DeployError(f"{template}: expected its access_control block last")
    at = _installed(fleet / "base", local)
    head = _substitute(head, "router.json5", {'"/etc/armfusion/tls/': f'"{at}/tls/',
                                              '"tls/127.0.0.1:7448"': json.dumps(base_endpoint)})
    body = json.dumps(acl, indent=2).replace("\n", "\n  ")
    return (f"// Written by armfusion deploy for the chairs {', '.join(chairs)}: run it again to add one.\n"
            f"{head}\n  access_control: {body},\n}}\n")


def _base_endpoint_of(base_config: Path) -> str | None:
    """The base router's endpoint a base-station node's config connects to (None: no config yet)."""
    if not base_config.is_file():
        return None
    import zenoh

    endpoints = json.loads(zenoh.Config.from_file(str(base_config)).get_json("connect/endpoints"))
    return endpoints[0] if endpoints else None


def fleet_chairs(fleet: Path) -> tuple[str, ...]:
    """The chairs with a certificate in ``fleet``, sorted."""
    return tuple(sorted(p.parent.parent.name for p in fleet.glob("*/tls/*.pem")
                        if p.stem == p.parent.parent.name and p.parent.parent.name not in BASE_NAMES))


def deploy(fleet: Path, chairs: list[str], *, base_address: str | None = None, base_port: int | None = None,
           chair_port: int = 7447, local: bool = False, force: bool = False) -> DeployReport:
    """Write ``chairs``' bundles, and the CA and base station's on first use (see the module's
    docstring). ``base_address``, ``base_port``: the base router's (``None``: those its files
    were made for, else ``127.0.0.1``, ``7448``); others than those its files were made for
    are refused."""
    for c in chairs:
        try:
            check_name(c, "chair")
        except ValueError as e:
            raise DeployError(str(e)) from None
        if c in BASE_NAMES:
            raise DeployError(f"chair {c!r}: the fleet's {', '.join(BASE_NAMES)} folders take these names")
    if len(set(chairs)) != len(chairs):
        raise DeployError(f"chairs {', '.join(chairs)}: a chair named twice")
    made_for = _base_endpoint_of(fleet / "base" / "zenoh" / "base.json5")
    old_host, _, old_port = (made_for or "tls/127.0.0.1:7448").removeprefix("tls/").rpartition(":")
    base_address = old_host.strip("[]") if base_address is None else base_address
    base_port = int(old_port) if base_port is None else base_port
    try:
        ip = ipaddress.ip_address(base_address)
    except ValueError:
        raise DeployError(f"--base-address {base_address!r}: expected a literal IP address "
                          "(the base router's certificate names it)") from None
    for what, port in (("--base-port", base_port), ("--chair-port", chair_port)):
        if not 1 <= port <= 65535:
            raise DeployError(f"{what} {port}: expected 1 to 65535")
    host = f"[{ip}]" if ip.version == 6 else str(ip)
    base_endpoint = f"tls/{host}:{base_port}"
    if made_for is not None and made_for != base_endpoint:
        raise DeployError(f"{fleet / 'base'}: the base station's files were made for {made_for} (its "
                          f"router's certificate names that address), not {base_endpoint}: leave out "
                          "--base-address and --base-port, or remove that folder to make them again")
    existing = [str(fleet / c) for c in chairs if (fleet / c).exists()]
    if existing and not force:
        raise DeployError(f"{', '.join(existing)} exist{'s' if len(existing) == 1 else ''}: --force to "
                          "replace (new certificates and passwords: the chair's nodes need the new files)")
    chair_endpoint = f"tcp/127.0.0.1:{chair_port}"
    report = DeployReport(fleet)
    made: list[Path] = []
    _folder(fleet)
    if not (fleet / "ca" / "ca.pem").is_file():
        make_ca(fleet / "ca")
        made += [fleet / "ca" / "ca.key", fleet / "ca" / "ca.pem"]
    base = _folder(fleet / "base")
    if not (base / "tls" / "router.pem").is_file():
        make_certificate(fleet / "ca", base / "tls", "router", f"IP:{ip}")
        make_certificate(fleet / "ca", base / "tls", "base", "DNS:base")
        _folder(base / "zenoh")
        at = _installed(base, local)
        text = (DEPLOY_CONFIG_DIR / "base.json5").read_text(encoding="utf-8")
        _write(base / "zenoh" / "base.json5", _substitute(text, "base.json5", {
            '"/etc/armfusion/tls/': f'"{at}/tls/', '"tls/127.0.0.1:7448"': json.dumps(base_endpoint)}))
        made += [*sorted((base / "tls").iterdir()), base / "zenoh" / "base.json5"]
    for c in chairs:
        if (fleet / c).exists():
            shutil.rmtree(fleet / c)
        made += _chair_files(fleet, c, base_endpoint, chair_endpoint, local)
        report.chairs[c] = fleet / c
    report.fleet_chairs = fleet_chairs(fleet)
    _write(base / "zenoh" / "router.json5", _base_router(fleet, report.fleet_chairs, base_endpoint, local))
    made.append(base / "zenoh" / "router.json5")
    report.made = [p.relative_to(fleet).as_posix() for p in made]
    return report
