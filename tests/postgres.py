"""A throw-away PostgreSQL server for tests, with server binaries from the `pgserver` wheel.

Only pgserver's bundled binaries are used, not its Python API: as root, that API adds a system user and
opens every parent folder of its data and binaries to all users. PostgreSQL refuses to run as root, so as
root the binaries are copied into the server's temporary folder, and run there as the user `nobody`.
"""

import contextlib
import importlib.util
import os
import pwd
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import sqlalchemy

INSTALL_HINT = 'pip install "pgserver>=0.1.4" "psycopg[binary]>=3.1"'
PORT = 5432  # names the unix socket only: the server listens on no TCP address
USER = "postgres"  # the database superuser, trusted without a password
DRIVER = "postgresql+psycopg"  # psycopg 3: SQLAlchemy 2.1's default for postgresql://, named for 2.0 too


class PostgresUnavailable(RuntimeError):
    """The PostgreSQL server binaries or the psycopg (3) driver are not installed."""


def site_dir() -> Path:
    """The folder holding pgserver's `pgserver/pginstall/` and the `pgserver.libs/` (libpq) that its binaries load."""
    spec = importlib.util.find_spec("pgserver")
    if spec is None or not spec.submodule_search_locations or importlib.util.find_spec("psycopg") is None:
        raise PostgresUnavailable(f"a PostgreSQL server for tests needs: {INSTALL_HINT}")
    return Path(spec.submodule_search_locations[0]).parent


def _run_as(uid: int | None, cwd: Path, *args: str | Path) -> None:
    """Run a command in `cwd`, as user `uid` with its primary group and no other group when given."""
    drop = {} if uid is None else {"user": uid, "group": pwd.getpwuid(uid).pw_gid, "extra_groups": []}
    result = subprocess.run([str(arg) for arg in args], cwd=cwd, capture_output=True, text=True, **drop)
    if result.returncode != 0:
        raise RuntimeError(f"{args[0]} failed ({result.returncode}):\n{result.stdout}{result.stderr}")


@contextlib.contextmanager
def postgres_server(database: str = "test") -> Iterator[str]:
    """Start a PostgreSQL server in a temporary folder, create `database` and yield its SQLAlchemy URL.

    The server listens only on a unix socket in that folder. It is stopped and the folder deleted on exit,
    also when the body raises. The URL has the form `postgresql+psycopg://postgres@/DATABASE?host=FOLDER`,
    which Optuna's storage (and any other process on this machine) accepts.
    """
    site = site_dir()
    base = Path(tempfile.mkdtemp(prefix="pg-"))  # short: a unix socket path has at most 107 bytes
    uid = None
    try:
        if os.geteuid() == 0:
            uid = pwd.getpwnam("nobody").pw_uid
            # the binaries find libpq at $ORIGIN/../../../pgserver.libs and share/ at ../share: keep that layout
            for part in ["pginstall/bin", "pginstall/lib/postgresql", "pginstall/share"]:
                shutil.copytree(site / "pgserver" / part, base / "pgserver" / part)
            shutil.copytree(site / "pgserver.libs", base / "pgserver.libs")
            site = base
            os.chown(base, uid, -1)
        bin_dir = site / "pgserver" / "pginstall" / "bin"
        data = base / "data"
        _run_as(uid, base, bin_dir / "initdb", "-D", data, "-U", USER, "--auth=trust", "-E", "UTF8", "--no-locale", "-N")
        with open(data / "postgresql.conf", "a") as conf:
            conf.write(f"listen_addresses = ''\nunix_socket_directories = '{base}'\nport = {PORT}\nfsync = off\n")
        try:
            _run_as(uid, base, bin_dir / "pg_ctl", "start", "-w", "-t", "60", "-D", data, "-l", base / "server.log")
            engine = sqlalchemy.create_engine(f"{DRIVER}://{USER}@/postgres?host={base}", isolation_level="AUTOCOMMIT")
            with engine.connect() as connection:
                connection.execute(sqlalchemy.text(f'CREATE DATABASE "{database}"'))
            engine.dispose()
            yield f"{DRIVER}://{USER}@/{database}?host={base}"
        finally:
            if (data / "postmaster.pid").exists():
                _run_as(uid, base, bin_dir / "pg_ctl", "stop", "-w", "-m", "fast", "-D", data)
    finally:
        shutil.rmtree(base, ignore_errors=True)
