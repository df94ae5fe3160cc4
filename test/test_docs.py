"""The documentation: the README a user reads and the pages of docs/, linked and current.

The configuration reference's parameter tables are the rendering of the configuration and node
parameters (:mod:`kentreg_ros.docs`); the README's headline table and docs/live.md's table are
the rendering of the committed benchmark results (``benchmarks/render_readme.py``); every page
of docs/ is linked from the README or docs/index.md, and every relative link resolves, anchors
included.
"""

from __future__ import annotations

import re
import sys
import tempfile
from pathlib import Path

import pytest
import yaml

from kentreg_ros import docs
from kentreg_ros.core import KentRegConfig, iter_fields
from kentreg_ros.io.params import PARAMETERS

REPO_ROOT = Path(__file__).resolve().parents[1]
README = REPO_ROOT / 'README.md'
DOCS = REPO_ROOT / 'docs'
CONFIGURATION = REPO_ROOT / docs.PAGE
#: The pages whose links are checked: the READMEs and every page of docs/.
PAGES = sorted([README, REPO_ROOT / 'benchmarks' / 'README.md', REPO_ROOT / 'bags' / 'README.md'])
PAGES += sorted(DOCS.glob('*.md'))
#: A user's page: KISS-ICP's README is ~100 lines, the house issue's bar 200.
README_MAX_LINES = 200


def _page_block(path: Path = CONFIGURATION) -> str:
    text = path.read_text(encoding='utf-8')
    return text.split(docs.BEGIN + '\n', 1)[1].split(docs.END, 1)[0]


def test_configuration_page_parameter_tables_equal_the_rendering() -> None:
    assert _page_block() == docs.render_parameters() + '\n', (
        f'{docs.PAGE} is stale: run python3 -m kentreg_ros.docs --write {docs.PAGE}'
    )
    assert docs.main(['--check', str(CONFIGURATION)]) == 0


def test_research_table_has_one_row_per_config_field_with_default_and_range() -> None:
    block = docs.render_research()
    for name, _, f in iter_fields(KentRegConfig()):
        rows = [line for line in block.splitlines() if line.startswith(f'| `{name}` |')]
        assert len(rows) == 1, name
        assert f.metadata['description'].split()[0] in rows[0]
    row = next(r for r in block.splitlines() if r.startswith('| `em.max_iterations` |'))
    assert row.startswith('| `em.max_iterations` | integer | `50` | 1 … 10000 | ')
    row = next(r for r in block.splitlines() if r.startswith('| `refine.method` |'))
    assert '`plane_to_plane`, `point_to_plane`, `none`' in row


def test_parameter_table_has_one_row_per_parameter() -> None:
    block = docs.render_parameters()
    assert PARAMETERS  # the loop below must not pass on nothing
    for p in PARAMETERS:
        rows = [line for line in block.splitlines() if line.startswith(f'| `{p.name}` |')]
        assert len(rows) == 1, p.name
        assert rows[0].endswith('Read-only: set at start-up. |') == p.read_only, rows[0]
    row = next(r for r in block.splitlines() if r.startswith('| `max_range` |'))
    assert row.startswith('| `max_range` | double | `0.0` | 0.0 … 10000.0 | ')
    assert '(`preprocess.max_range`)' in row  # the research field behind it


def test_every_key_of_the_shipped_parameter_file_is_documented() -> None:
    data = yaml.safe_load((REPO_ROOT / 'config' / 'kentreg.yaml').read_text(encoding='utf-8'))
    params = data['/**']['ros__parameters']
    documented = {r.name for r in docs.product_parameters()}
    assert sorted(set(params) - documented) == []


def test_write_then_check_round_trip_and_stale_file_is_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    readme = tmp_path / 'README.md'
    readme.write_text(
        f'# x\n\nbefore\n{docs.BEGIN}\nold table\n{docs.END}\nafter\n'
        f'{docs.RESEARCH_BEGIN}\n{docs.RESEARCH_END}\n'
    )
    assert docs.main(['--check', str(readme)]) == 1
    assert 'out of date' in capsys.readouterr().err
    assert docs.main(['--write', str(readme)]) == 0
    text = readme.read_text()
    assert text.startswith(f'# x\n\nbefore\n{docs.BEGIN}\n')
    assert f'{docs.END}\nafter\n' in text
    assert 'old table' not in text and '| `max_range` |' in text and '| `mode` |' in text
    assert docs.main(['--check', str(readme)]) == 0


def test_missing_markers_are_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    readme = tmp_path / 'README.md'
    readme.write_text(f'# x\n{docs.END}\n{docs.BEGIN}\n')
    assert docs.main(['--check', str(readme)]) == 2
    assert 'expected one line' in capsys.readouterr().err
    with pytest.raises(ValueError, match='found 0 and 0'):
        docs.replace_block('no markers', 'table')


def test_readmes_quote_the_committed_benchmark_results() -> None:
    """Every generated block of README.md, docs/live.md and benchmarks/README.md equals what
    benchmarks/render_readme.py computes from benchmarks/results/ (numbers from one source)."""
    if str(REPO_ROOT) not in sys.path:
        sys.path.insert(0, str(REPO_ROOT))
    from benchmarks import render_readme

    assert render_readme.main(['--check']) == 0


def test_the_models_block_compares_the_two_models_on_every_recording() -> None:
    """The README's choice of model: a ratio per recording, the map-consistent columns only
    where the run scored against it, and no block without any result."""
    if str(REPO_ROOT) not in sys.path:
        sys.path.insert(0, str(REPO_ROOT))
    from benchmarks.render_readme import models_block

    def m(ate: float, cons: float | None = None) -> dict[str, object]:
        metrics: dict[str, object] = {'ate': {'rmse': ate}}
        if cons is not None:
            metrics['ate_consistent_m'] = cons
        return {'metrics': metrics}

    odometry = {'machine': {'git': 'abc1234'},
                'methods': {'kentreg': m(0.010, 0.004), 'kentreg_local_map': m(0.008, 0.002)},
                'strides': {'4': {'kentreg': m(0.02), 'kentreg_local_map': m(0.01)}}}  # fmt: skip
    livox = {'machine': {'git': 'def5678'}, 'sequences': [
        {'name': 'hku_2',
         'methods': {'kentreg': {'ate_m': 0.2}, 'kentreg_local_map': {'ate_m': 0.05}}}
    ]}  # fmt: skip
    text = models_block(odometry, livox, None)
    assert text is not None
    assert (
        '| BALM sample, every scan | 10.0 mm | 8.0 mm | 0.80× | 4.0 mm | 2.0 mm | 0.50× |' in text
    )
    assert '| Livox Avia hku_2, keyframes | 0.200 m | 0.050 m | 0.25× | – | – | – |' in text
    assert 'every 4th' not in text and 'abc1234' in text and 'def5678' in text
    assert models_block(None, None, None) is None


def test_readme_is_a_page_a_user_reads() -> None:
    """The README keeps the two commands, the robot, the headline and the links; the rest is in
    docs/."""
    text = README.read_text(encoding='utf-8')
    assert len(text.splitlines()) <= README_MAX_LINES
    for command in (
        "python3 -m pip install -e '.[io,fast]' && kentreg_replay bags/balm_50",
        'bash test/run_tests.sh',
        'python3 -m pytest -m "not integration"',
    ):
        assert command in text, command


_FENCE = re.compile(r'^(```|~~~).*?^\1', re.M | re.S)
_LINK = re.compile(r'\[[^\]]*\]\(([^()\s]+)\)')
_HEADING = re.compile(r'^#{1,6}\s+(.+?)\s*#*$', re.M)


def _prose(text: str) -> str:
    """``text`` without its fenced code blocks (links and headings there are code)."""
    return _FENCE.sub('', text)


def _anchor(heading: str) -> str:
    """GitHub's anchor of a heading: its text (links and code marks taken off) in lower case,
    without punctuation, spaces as hyphens."""
    text = re.sub(r'\[([^\]]*)\]\([^)]*\)', r'\1', heading).replace('`', '').replace('*', '')
    return re.sub(r'[^\w\- ]', '', text.strip().lower()).replace(' ', '-')


def anchors(path: Path) -> set[str]:
    """Every anchor of the headings of ``path`` (repeats numbered as GitHub numbers them)."""
    found: set[str] = set()
    for heading in _HEADING.findall(_prose(path.read_text(encoding='utf-8'))):
        base = _anchor(heading)
        name, n = base, 0
        while name in found:
            n += 1
            name = f'{base}-{n}'
        found.add(name)
    return found


def relative_links(path: Path) -> list[str]:
    """The relative link targets of ``path`` (not web addresses), outside code blocks."""
    targets = _LINK.findall(_prose(path.read_text(encoding='utf-8')))
    return [t for t in targets if not re.match(r'[a-z][a-z0-9+.-]*:', t)]


def test_anchor_and_links_follow_githubs_rules(tmp_path: Path) -> None:
    page = tmp_path / 'p.md'
    page.write_text(
        '# The local map (`odometry.model: local_map`)\n\n## Notes\n\n## Notes\n\n'
        '```md\n# not a heading [x](nowhere.md)\n```\n'
        'See [a](other.md#notes-1), [b](https://example.com) and [c](#notes).\n'
    )
    assert anchors(page) == {'the-local-map-odometrymodel-local_map', 'notes', 'notes-1'}
    assert relative_links(page) == ['other.md#notes-1', '#notes']


@pytest.mark.parametrize('page', PAGES, ids=lambda p: str(p.relative_to(REPO_ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    """Every relative link names a file or folder of the repository, and an anchor of a
    Markdown page names one of its headings."""
    broken = []
    for target in relative_links(page):
        name, _, fragment = target.partition('#')
        path = (page.parent / name).resolve() if name else page
        if not path.exists():
            broken.append(f'{target} (no such file)')
        elif fragment and path.suffix == '.md' and fragment not in anchors(path):
            broken.append(f'{target} (no such heading)')
    assert broken == [], f'{page.relative_to(REPO_ROOT)}: {broken}'


def test_every_docs_page_is_linked_from_the_readme_or_the_index() -> None:
    index = DOCS / 'index.md'
    linked = {(README.parent / t.partition('#')[0]).resolve() for t in relative_links(README)}
    linked |= {(index.parent / t.partition('#')[0]).resolve() for t in relative_links(index)}
    assert index.resolve() in linked
    unlinked = sorted(p.name for p in DOCS.glob('*.md') if p.resolve() not in linked)
    assert unlinked == [], f'pages of docs/ linked from neither README.md nor index.md: {unlinked}'


#: What a path of the machine that ran a benchmark looks like (a checkout, the shared data, a
#: temporary folder, a home): a reader of the repository has none of these.
MACHINE_PATH = re.compile(r'(?<![\w.$])/(?:work|tmp|root|home|Users)/')


@pytest.mark.parametrize(
    'path',
    sorted(
        p for p in (REPO_ROOT / 'benchmarks' / 'results').glob('*') if p.suffix in ('.md', '.json')
    ),
    ids=lambda p: p.name,
)
def test_committed_results_name_data_relative_to_the_repository(path: Path) -> None:
    """Result files name data as a clone finds it (``../shared/data/balm``,
    ``bags/balm_50``, ``$TMPDIR/...`` for a run's output folder), not by the path of the
    machine that ran them."""
    found = sorted({m.group(0) for m in MACHINE_PATH.finditer(path.read_text(encoding='utf-8'))})
    assert found == [], f'{path.name} names machine paths: {found}'


def test_benchmark_writer_names_paths_relative_to_the_repository() -> None:
    sys.path.insert(0, str(REPO_ROOT))
    from benchmarks.harness import report

    text = (
        f'{REPO_ROOT}/bags/balm_50 {REPO_ROOT.parent}/shared/data/balm {tempfile.gettempdir()}/x'
    )
    # A clone made directly in the temporary folder (/tmp/kentreg_ros) has its neighbours there:
    # the temporary folder is then its parent, named as such.
    in_tmp = Path(tempfile.gettempdir()).resolve() == REPO_ROOT.parent.resolve()
    tmp_name = '../x' if in_tmp else '$TMPDIR/x'
    assert report.relative_paths(text) == f'bags/balm_50 ../shared/data/balm {tmp_name}'
