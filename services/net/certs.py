"""`tpdeb-certs`: a private certificate authority and a router certificate for `tls/` endpoints.

    tpdeb-certs DIR [--hosts 127.0.0.1,localhost] [--days 365] [--users U,…]
                    [--force | --if-missing]

writes `ca.pem`/`ca.key` (a self-signed CA) and `router.pem`/`router.key` (the router's
certificate, signed by that CA, naming every host as a DNS or IP subject alternative name).
Services get `--tls-ca DIR/ca.pem`; the router gets `--tls-cert DIR/router.pem --tls-key
DIR/router.key`. Clients check the router's name against those hosts, so list every name or
address they connect to. `--users replay,learner,actor` also writes a random password per user,
`{user}.password`, and the router's dictionary of them, `users.txt` (its `--auth-file`); each
service reads its own with `--password-file`. Keys and passwords are written 0600 and existing
files are never replaced without `--force` (`--if-missing` leaves a complete set as it is: an
init step run at every start).
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import os
import re
import sys
from pathlib import Path

from tpdeb.services.config import ConfigError, Parser

PROG = "tpdeb-certs"
FILES = ("ca.pem", "ca.key", "router.pem", "router.key")
DEFAULT_HOSTS = ("127.0.0.1", "localhost")
MAX_DAYS = 36_500
_DNS_LABEL = r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)"
_DNS_NAME = re.compile(rf"{_DNS_LABEL}(\.{_DNS_LABEL})*")


def parse_hosts(text: str | list[str] | tuple[str, ...], where: str = "--hosts") -> list[str]:
    """Comma- or space-separated host names and IP addresses, each checked."""
    if isinstance(text, str):
        text = text.replace(",", " ").split()
    hosts = [h.strip() for h in text if h.strip()]
    if not hosts:
        raise ConfigError("--hosts is empty: name at least one host clients connect to, e.g. "
                          "--hosts 127.0.0.1,localhost")
    for host in hosts:
        try:
            ipaddress.ip_address(host)
        except ValueError:
            if len(host) > 253 or not _DNS_NAME.fullmatch(host):
                raise ConfigError(f"{where}: {host!r} is neither an IP address nor a DNS name "
                                  "(e.g. 10.0.0.5, learner.example.org)") from None
    return hosts


def _alt_names(hosts: list[str]):
    from cryptography import x509

    names = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)


def _write(path: Path, data: bytes, mode: int) -> None:
    # Created with its final mode (a key is never readable by others, not even for a moment),
    # and exclusively: a file that appeared since the check is not clobbered.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "wb") as out:
        out.write(data)
    os.chmod(path, mode)  # the umask may have narrowed it


def write_certs(directory: str | Path, hosts=DEFAULT_HOSTS, days: int = 365,
                force: bool = False) -> dict[str, Path]:
    """Write a CA and a router certificate signed by it into `directory`; returns the paths by
    file name. Refuses (ConfigError) to replace existing files unless `force`."""
    from cryptography.hazmat.primitives import serialization

    hosts = parse_hosts(hosts)
    if isinstance(days, bool) or not isinstance(days, int) or not 1 <= days <= MAX_DAYS:
        raise ConfigError(f"--days {days!r}: must be a whole number of days in [1, {MAX_DAYS}]")
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise ConfigError(f"{directory} is a file, not a directory: name a directory for the "
                          "certificates")
    paths = {name: directory / name for name in FILES}
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not force:
        raise ConfigError(f"{', '.join(existing)} already exist(s): pass --force to replace "
                          "them (every client must then be given the new ca.pem)")
    directory.mkdir(parents=True, exist_ok=True)
    (ca_cert, ca_key), (router_cert, router_key) = _certificates(hosts, days)

    def key_pem(key) -> bytes:
        return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                 serialization.NoEncryption())

    contents = {"ca.pem": (ca_cert.public_bytes(serialization.Encoding.PEM), 0o644),
                "ca.key": (key_pem(ca_key), 0o600),
                "router.pem": (router_cert.public_bytes(serialization.Encoding.PEM), 0o644),
                "router.key": (key_pem(router_key), 0o600)}
    for name, (data, mode) in contents.items():
        if force:
            paths[name].unlink(missing_ok=True)
        _write(paths[name], data, mode)
    return paths


def _key_usage(x509, signs_certificates: bool):
    return x509.KeyUsage(
        digital_signature=not signs_certificates, content_commitment=False,
        key_encipherment=False, data_encipherment=False, key_agreement=False,
        key_cert_sign=signs_certificates, crl_sign=signs_certificates, encipher_only=False,
        decipher_only=False)


def _certificates(hosts: list[str], days: int) -> tuple[tuple, tuple]:
    """(CA certificate, its key), (router certificate for `hosts`, its key): P-256, SHA-256,
    valid from five minutes ago for `days` days."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.timezone.utc)
    start, end = now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "TPDEB private CA")])
    ca_cert = (
        x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name)
        .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
        .not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(x509, signs_certificates=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()),
                       critical=False)
        .sign(ca_key, hashes.SHA256()))
    router_key = ec.generate_private_key(ec.SECP256R1())
    router_cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, hosts[0])]))
        .issuer_name(ca_name).public_key(router_key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(x509, signs_certificates=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .add_extension(_alt_names(hosts), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                       critical=False)
        .sign(ca_key, hashes.SHA256()))
    return (ca_cert, ca_key), (router_cert, router_key)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = Parser(prog=PROG, description=__doc__.split("\n\n")[0],
                                epilog=__doc__.split("\n\n", 2)[2],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dir", metavar="DIR", help="directory to write ca.pem, ca.key, router.pem, "
                   "router.key into (created if missing)")
    p.add_argument("--hosts", default=",".join(DEFAULT_HOSTS),
                   help="comma-separated names and addresses clients reach the router by "
                   "(default: %(default)s)")
    p.add_argument("--days", default="365", help="validity in days (default: %(default)s)")
    p.add_argument("--users", default="", help="comma-separated users to write a password for "
                   "({user}.password) and the router's users.txt")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--force", action="store_true", help="replace existing files")
    mode.add_argument("--if-missing", action="store_true",
                      help="do nothing when DIR already holds every file")
    return p.parse_args(argv)


def write_passwords(directory: str | Path, users: list[str], force: bool = False) -> dict:
    """A random password per user in `directory` ({user}.password) and the router's users.txt,
    all readable by their owner only."""
    from tpdeb.services.net.security import new_passwords, write_auth_file

    directory = Path(directory)
    passwords = new_passwords(users)
    paths = {f"{user}.password": directory / f"{user}.password" for user in passwords}
    existing = [str(p) for p in (*paths.values(), directory / "users.txt") if p.exists()]
    if existing and not force:
        raise ConfigError(f"{', '.join(existing)} already exist(s): pass --force to replace them")
    directory.mkdir(parents=True, exist_ok=True)
    for user, password in passwords.items():
        paths[f"{user}.password"].unlink(missing_ok=True)
        _write(paths[f"{user}.password"], f"{password}\n".encode(), 0o600)
    paths["users.txt"] = write_auth_file(directory / "users.txt", passwords)
    return paths


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        try:
            days = int(args.days)
        except ValueError:
            raise ConfigError(f"--days {args.days!r}: must be a whole number of days in "
                              f"[1, {MAX_DAYS}]") from None
        users = [u.strip() for u in args.users.split(",") if u.strip()]
        wanted = [*FILES, *(f"{u}.password" for u in users), *(["users.txt"] if users else [])]
        if args.if_missing and all((Path(args.dir) / name).is_file() for name in wanted):
            print(f"{PROG}: {args.dir} holds every file already; nothing written")
            return 0
        paths = write_certs(args.dir, parse_hosts(args.hosts), days, args.force or args.if_missing)
        if users:
            paths.update(write_passwords(args.dir, users, args.force or args.if_missing))
    except ConfigError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"{PROG}: error: cannot write into {args.dir}: {exc.strerror} ({exc.filename})",
              file=sys.stderr)
        return 2
    print(f"{PROG}: wrote {', '.join(str(p) for p in paths.values())}")
    auth = f" --auth-file {paths['users.txt']}" if users else ""
    user = f" --user U --password-file {args.dir}/U.password" if users else ""
    print(f"{PROG}: router: --tls-cert {paths['router.pem']} --tls-key {paths['router.key']}"
          f"{auth}; every service: --tls-ca {paths['ca.pem']}{user}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
