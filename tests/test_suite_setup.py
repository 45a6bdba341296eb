"""The test run itself: what the README's test command relies on."""

import pytest


@pytest.mark.xdist_group("suite-setup")
def test_xdist_groups_keep_their_tests_together(request):
    """The costly shared fixtures (a fleet's merge, the sample negative pair's alignment)
    are computed once because their tests run on one worker (``xdist_group`` under
    ``--dist loadgroup``). pytest-xdist marks a grouped test by its node id ending in
    ``@group``; pytest 9.2 dropped that without a word (pytest-dev/pytest-xdist#1386),
    and each worker then computed them again (the fleet merge: 73 s on both workers in
    one CI run). Run by pytest-xdist with loadgroup only."""
    config = request.config
    if not hasattr(config, "workerinput") or not getattr(config.option, "loadgroup", False):
        pytest.skip("not a pytest-xdist worker under --dist loadgroup")
    assert request.node.nodeid.endswith("@suite-setup"), (
        f"{request.node.nodeid}: pytest-xdist's groups are ignored by this pytest "
        f"({pytest.__version__}); see pyproject.toml's test extras"
    )
