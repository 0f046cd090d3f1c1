"""The test suite's own ROS domains (conftest.fresh_domain_id): in range, apart, never crossing."""

import itertools

from conftest import (DOMAINS_PER_SUITE, FIRST_TEST_DOMAIN, LAST_DOMAIN, SLICES,
                      suite_domains)


def test_every_caller_domain_gets_a_slice_in_range_without_its_own_domain():
    for caller in range(LAST_DOMAIN + 1):
        for worker, workers in ((0, 1), (0, 2), (1, 2), (3, 4)):
            domains = list(suite_domains(caller, worker, workers))
            assert len(domains) == DOMAINS_PER_SUITE
            assert FIRST_TEST_DOMAIN <= min(domains) and max(domains) <= LAST_DOMAIN
            assert caller not in domains


def test_the_workers_of_one_run_never_share_a_test_domain():
    # scripts/test.sh spreads the ROS graph tests over pytest-xdist's workers too
    for workers in (2, 3, 8):
        for caller in range(LAST_DOMAIN + 1):
            slices = [set(suite_domains(caller, worker, workers)) for worker in range(workers)]
            for a, b in itertools.combinations(slices, 2):
                assert not a & b, (caller, workers)


def test_callers_that_differ_modulo_slices_never_share_a_test_domain():
    # the callers of the usual range, 0..100 (scripts/test.sh and .ci/run pick 1..100)
    for a, b in itertools.combinations(range(101), 2):
        if a % SLICES != b % SLICES:
            assert not set(suite_domains(a)) & set(suite_domains(b)), (a, b)


def test_test_domains_stay_above_the_callers_range():
    used = set().union(*(suite_domains(caller) for caller in range(LAST_DOMAIN + 1)))
    assert min(used) == FIRST_TEST_DOMAIN > 100
