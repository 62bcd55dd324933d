"""
The README's WARN table speaks of messages the code writes: each row's quoted start is found.

The table ("When `/diagnostics` says WARN") quotes the start of each message; a message renamed
in the code without the table fails here. Placeholders are cut at the first ``(``, ``...`` or
``:``, and each part split on `` / `` must occur in a source file of ``dgp_ros``.
"""
import os
import re

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _sources() -> str:
    out = []
    for root, _, files in os.walk(os.path.join(REPO, 'dgp_ros')):
        out += [open(os.path.join(root, f)).read() for f in files if f.endswith('.py')]
    # a message is often split over string literals: join adjacent ones
    return re.sub(r"'\s*\n\s*f?'", '', '\n'.join(out))


def test_every_warn_row_quotes_a_message_of_the_code():
    text = open(os.path.join(REPO, 'README.md')).read()
    sec = text.split('## When `/diagnostics` says WARN', 1)[1].split('\n## ', 1)[0]
    rows = [r for r in sec.splitlines() if r.startswith('| `')]
    assert len(rows) >= 10, rows
    src = _sources()
    for row in rows:
        cell = row.split('|')[1]
        for quote in re.findall(r'`([^`]+)`', cell):
            start = re.split(r' \(|\.\.\.|:| k/', quote)[0].strip()
            assert len(start) >= 8 and start in src, (quote, start)
