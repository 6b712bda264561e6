"""What `pip install` would use here, as `uv pip install`'s flags (for scripts/bootstrap.sh).

    .venv/bin/python scripts/uv_flags.py

pip's own option parser reads its settings (every config file in pip's order, the sections
`global` then `install`, the PIP_* variables over them, empty ones ignored), so uv resolves
from the same indexes, links and constraints as pip would. Printed one item a line: first
`env NAME=VALUE` lines (the environment uv gets: pip's certificate as SSL_CERT_FILE and its
timeout as UV_HTTP_TIMEOUT, where the environment sets neither), then uv's flags and their
values. pip counts every index alike; uv's `--index-strategy unsafe-best-match` does the same.

Exit 3 with one line on stderr where uv would not do what pip does: a pip without that parser
(its internals moved), or a setting with no uv flag here (a proxy or client certificate in
pip's config, binary-only or source-only packages, prefer-binary, required hashes). The
bootstrap then installs with pip.
"""

from __future__ import annotations

import os
import sys


def settings() -> tuple[list[str], list[str]]:
    from pip._internal.commands import create_command
    options, _ = create_command('install').parse_args([])
    unsupported = [name for name, value in (
        ('proxy', options.proxy), ('client-cert', options.client_cert),
        ('no-binary', options.format_control.no_binary),
        ('only-binary', options.format_control.only_binary),
        ('prefer-binary', options.prefer_binary), ('require-hashes', options.require_hashes))
        if value]
    if unsupported:
        raise LookupError(f'pip is set up with {", ".join(unsupported)}, which the bootstrap '
                          'does not hand to uv')
    env = []
    if options.cert and not os.environ.get('SSL_CERT_FILE'):
        env.append(f'SSL_CERT_FILE={options.cert}')
    if options.timeout and not os.environ.get('UV_HTTP_TIMEOUT'):
        env.append(f'UV_HTTP_TIMEOUT={max(1, round(options.timeout))}')
    flags = ['--index-strategy', 'unsafe-best-match']
    if options.no_index:
        flags.append('--no-index')
    else:
        flags += ['--index-url', options.index_url]
        for url in options.extra_index_urls:
            flags += ['--extra-index-url', url]
    for where in options.find_links:
        flags += ['--find-links', where]
    for path in options.constraints:
        flags += ['--constraint', path]
    for host in options.trusted_hosts:
        flags += ['--allow-insecure-host', host]
    if options.pre:
        flags += ['--prerelease', 'allow']
    return env, flags


def main() -> int:
    try:
        env, flags = settings()
    except Exception as error:           # noqa: BLE001 - any failure means: let pip install
        print(f'uv_flags: {error}', file=sys.stderr)
        return 3
    for item in env:
        print(f'env {item}')
    for item in flags:
        print(item)
    return 0


if __name__ == '__main__':
    sys.exit(main())
