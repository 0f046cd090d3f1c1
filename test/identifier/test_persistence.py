"""
The state file (bcid_ros.identifier.persistence): exact continuation, and every refusal.

Each estimator is fed part of a scenario through the node's SampleFeeder,
saved, restored into a fresh estimator and feeder, and both are continued
with the same samples: the restored pair must give the same estimates as
the uninterrupted one. Files from another configuration, truncated,
damaged, of a newer format, or holding pickled objects are refused with
one line; a failed save leaves the old file intact.
"""

from pathlib import Path

import numpy as np
import pytest

from bcid_ros.identifier import persistence
from bcid_ros.identifier.feeder import SampleFeeder
from bcid_ros.identifier.parameters import (check_identifier_parameters, estimator_from_parameters,
                                            load_yaml_parameters)
from bcid_ros.simulation import make_scenario

CONFIG = Path(__file__).resolve().parents[2] / 'config'

# (config, estimator override, samples before the save, samples after it). The
# cl_bcls save lies between two redesigns (period 1000), bciv's after its idle phase.
CASES = [
    ('ding_miso', 'rls', 700, 600),
    ('ding_miso', 'bcrls', 700, 600),
    ('ikenoue_colored', 'bciv', 900, 600),
    ('ikeda_closed_loop', 'cl_bcls', 2300, 2000),
]


def settings_of(scenario, **changes):
    values = load_yaml_parameters(CONFIG / f'{scenario}.yaml')
    values.update(changes)
    return check_identifier_parameters(values)


def sample_rows(scenario, count, seed=3):
    y, u = make_scenario(scenario).simulate(count, seed)
    return np.column_stack([y, np.reshape(u, (count, -1))])


def feeder_of(settings):
    return SampleFeeder(estimator_from_parameters(settings), excitation_window=20,
                        publish_period=7)


def restore(settings, path):
    feeder = feeder_of(settings)
    sections = persistence.load_state(path, persistence.configuration_fingerprint(settings))
    persistence.restore_identifier(feeder.estimator, feeder, sections,
                                   settings['forgetting_factor'], path)
    return feeder


def save(settings, feeder, path):
    persistence.save_state(path, persistence.configuration_fingerprint(settings),
                           persistence.identifier_sections(feeder.estimator, feeder))


@pytest.mark.parametrize('scenario,estimator,before,after', CASES,
                         ids=[case[1] for case in CASES])
def test_restored_state_continues_exactly(tmp_path, scenario, estimator, before, after):
    settings = settings_of(scenario, estimator=estimator)
    rows = sample_rows(scenario, before + after)
    # the feeder's own state matters too: a NaN sample right before the save
    # leaves a regressor restart pending, a constant stretch an excitation count
    rows[before - 1, 0] = np.nan
    rows[before - 30:before - 5, 1] = 0.25
    uninterrupted = feeder_of(settings)
    uninterrupted.feed(rows[:before])
    path = tmp_path / 'state.npz'
    save(settings, uninterrupted, path)
    restored = restore(settings, path)
    assert restored.get_state() == uninterrupted.get_state()
    assert restored.get_state()['restart_pending']

    published = []
    for feeder in (uninterrupted, restored):
        estimates = []
        for row in rows[before:]:  # one message per sample, as the node gets them
            result = feeder.take_rows(row[np.newaxis])
            if result.estimates is not None:
                estimates.append(np.concatenate(result.estimates))
        published.append(np.array(estimates))
        assert feeder.estimator.ready
    np.testing.assert_allclose(published[1], published[0], rtol=0, atol=1e-9)
    assert len(published[0]) >= after // 7 - 1
    for name in ('theta', 'theta_uncompensated', 'noise'):
        np.testing.assert_allclose(getattr(restored.estimator, name),
                                   getattr(uninterrupted.estimator, name), rtol=0, atol=1e-9)
    assert restored.estimator.valid == uninterrupted.estimator.valid
    assert restored.estimator.flags == uninterrupted.estimator.flags
    assert restored.estimator.samples == uninterrupted.estimator.samples
    assert restored.get_state() == uninterrupted.get_state()


def test_fingerprint_ignores_live_and_transport_parameters_and_unset_defaults():
    base = persistence.configuration_fingerprint(settings_of('ikenoue_colored'))
    for changes in ({'forgetting_factor': 0.99}, {'publish_period': 5},
                    {'input_mode': 'separate'}, {'state_save_period': 1.0},
                    {'controller_numerator': [0.5]}):   # not a bciv option
        assert persistence.configuration_fingerprint(
            settings_of('ikenoue_colored', **changes)) == base
    unset = settings_of('ding_miso', estimator='bciv')
    default = settings_of('ding_miso', estimator='bciv',
                          idle_samples=persistence.configuration_fingerprint(unset)[
                              'idle_samples'])
    assert (persistence.configuration_fingerprint(unset)
            == persistence.configuration_fingerprint(default))


@pytest.mark.parametrize('changes,named', [
    ({'order': 3}, 'order'),
    ({'estimator': 'rls'}, 'estimator'),
    ({'feedthrough': True}, 'feedthrough'),
    ({'num_inputs': 3}, 'num_inputs'),
    ({'initial_covariance': 100.0}, 'initial_covariance'),
])
def test_another_configuration_is_refused_naming_the_difference(tmp_path, changes, named):
    settings = settings_of('ding_miso')
    feeder = feeder_of(settings)
    feeder.feed(sample_rows('ding_miso', 100))
    save(settings, feeder, tmp_path / 'state.npz')
    other = persistence.configuration_fingerprint(settings_of('ding_miso', **changes))
    with pytest.raises(persistence.StateRefused) as refused:
        persistence.load_state(tmp_path / 'state.npz', other)
    message = str(refused.value)
    assert 'another configuration' in message and named in message
    assert str(tmp_path / 'state.npz') in message and '\n' not in message


def test_estimator_options_are_part_of_the_fingerprint(tmp_path):
    settings = settings_of('ikenoue_colored')
    feeder = feeder_of(settings)
    feeder.feed(sample_rows('ikenoue_colored', 200))
    save(settings, feeder, tmp_path / 'state.npz')
    other = persistence.configuration_fingerprint(settings_of('ikenoue_colored', iv_lag=6))
    with pytest.raises(persistence.StateRefused, match='iv_lag 5 there, 6 here'):
        persistence.load_state(tmp_path / 'state.npz', other)


@pytest.fixture
def saved(tmp_path):
    settings = settings_of('ding_miso')
    feeder = feeder_of(settings)
    feeder.feed(sample_rows('ding_miso', 300))
    path = tmp_path / 'state.npz'
    save(settings, feeder, path)
    return path, persistence.configuration_fingerprint(settings)


@pytest.mark.parametrize('keep', [0.0, 0.1, 0.5, 0.9, 0.999])
def test_truncated_file_is_refused(saved, keep):
    path, fingerprint = saved
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * keep)])
    with pytest.raises(persistence.StateRefused, match='truncated or damaged'):
        persistence.load_state(path, fingerprint)


def test_damaged_bytes_are_refused(saved):
    path, fingerprint = saved
    data = bytearray(path.read_bytes())
    # a flipped bit inside an array: the zip's CRC-32 of that member catches it
    position = data.index(b'\x93NUMPY', data.index(b'estimator.p.npy')) + 200
    data[position] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(persistence.StateRefused, match='truncated or damaged'):
        persistence.load_state(path, fingerprint)


def test_newer_format_version_is_refused(saved, monkeypatch):
    path, fingerprint = saved
    settings = settings_of('ding_miso')
    feeder = feeder_of(settings)
    monkeypatch.setattr(persistence, 'VERSION', persistence.VERSION + 1)
    save(settings, feeder, path)
    monkeypatch.undo()
    with pytest.raises(persistence.StateRefused,
                       match=f'format version {persistence.VERSION + 1}, newer'):
        persistence.load_state(path, fingerprint)


def test_other_files_and_pickles_are_refused(tmp_path, saved):
    _, fingerprint = saved
    text = tmp_path / 'notes.npz'
    text.write_text('not a state\n')
    with pytest.raises(persistence.StateRefused, match='truncated or damaged'):
        persistence.load_state(text, fingerprint)
    foreign = tmp_path / 'foreign.npz'
    np.savez(foreign, theta=np.zeros(3))
    with pytest.raises(persistence.StateRefused, match='not a bcid_ros state file'):
        persistence.load_state(foreign, fingerprint)
    # an object array would need pickle to load, which may run code: never loaded
    pickled = tmp_path / 'pickled.npz'
    np.savez(pickled, header=np.array([{'format': persistence.FORMAT}], dtype=object))
    with pytest.raises(persistence.StateRefused, match='pickle'):
        persistence.load_state(pickled, fingerprint)


def test_missing_file_is_a_first_start_and_an_unreadable_one_is_refused(tmp_path):
    assert persistence.load_state(tmp_path / 'none.npz', {}) is None
    with pytest.raises(persistence.StateRefused, match='cannot be read'):
        persistence.load_state(tmp_path, {})   # a directory


def test_failed_save_keeps_the_old_file_and_leaves_no_temporary(saved, monkeypatch):
    path, fingerprint = saved
    before = path.read_bytes()

    def broken(*args, **kwargs):
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(np, 'savez', broken)
    with pytest.raises(OSError, match='No space'):
        persistence.save_state(path, fingerprint, {})
    assert path.read_bytes() == before
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def test_unwritable_directory_raises_oserror(tmp_path):
    with pytest.raises(OSError):
        persistence.save_state(tmp_path / 'missing' / 'state.npz', {}, {})
    blocker = tmp_path / 'file'
    blocker.write_text('')
    with pytest.raises(OSError):
        persistence.save_state(blocker / 'state.npz', {}, {})


def test_restore_refuses_a_section_of_other_dimensions(tmp_path):
    small = settings_of('ding_miso', estimator='rls')
    feeder = feeder_of(small)
    feeder.feed(sample_rows('ding_miso', 100))
    section = persistence.estimator_section(feeder.estimator)
    other = estimator_from_parameters(settings_of('ding_miso', estimator='rls', order=3))
    with pytest.raises(ValueError, match='does not match'):
        persistence.restore_estimator(other, section)


def test_a_section_that_does_not_fit_restores_neither_estimator_nor_feeder(tmp_path):
    settings = settings_of('ding_miso', estimator='rls')
    saved = feeder_of(settings)
    saved.feed(sample_rows('ding_miso', 100))
    sections = persistence.identifier_sections(saved.estimator, saved)
    sections['feeder'] = ({}, {'no such counter': 1})
    feeder = feeder_of(settings)
    feeder.feed(sample_rows('ding_miso', 30, seed=4))
    before = feeder.get_state()
    with pytest.raises(persistence.StateRefused, match='state file s.npz does not fit'):
        persistence.restore_identifier(feeder.estimator, feeder, sections, 1.0, 's.npz')
    assert feeder.get_state() == before
    assert feeder.estimator.samples == 0  # the estimator went back to its reset


# ------------------------------------------------------------------ values (SPEC §18)
def saved_sections(estimator='rls', count=300, scenario='ding_miso'):
    settings = settings_of(scenario, estimator=estimator)
    feeder = feeder_of(settings)
    if count:
        feeder.feed(sample_rows(scenario, count))
    return settings, persistence.identifier_sections(feeder.estimator, feeder)


def refused_after(tmp_path, change, match, estimator='rls'):
    """Save a good state changed by ``change(sections)``; assert that restoring refuses it."""
    settings, sections = saved_sections(estimator)
    change(sections)
    path = tmp_path / 'changed.npz'
    persistence.save_state(path, persistence.configuration_fingerprint(settings), sections)
    feeder = feeder_of(settings)
    with pytest.raises(persistence.StateRefused, match=match):
        restore(settings, path)
    assert feeder.estimator.samples == 0 and not feeder.estimator.valid


def test_nan_arrays_are_refused(tmp_path):
    def nan_theta(sections):
        sections['estimator'][0]['theta_ls'] = np.full(4 + 2, np.nan)
    refused_after(tmp_path, nan_theta, r'estimator.theta_ls holds NaN or Inf')


def test_arrays_of_another_dtype_are_refused(tmp_path):
    def int8_theta(sections):
        arrays = sections['estimator'][0]
        arrays['theta_ls'] = arrays['theta_ls'].astype(np.int8)
    refused_after(tmp_path, int8_theta, r'estimator.theta_ls has dtype int8, expected float64')


@pytest.mark.parametrize('counter', ['used', 'since_publish', 'nonfinite'])
def test_negative_counts_are_refused(tmp_path, counter):
    def negative(sections):
        sections['feeder'][1][counter] = -5
    refused_after(tmp_path, negative, f'feeder.{counter} is -5, expected a count >= 0')


def test_a_covariance_that_is_not_positive_definite_is_refused(tmp_path):
    def indefinite(sections):
        sections['estimator'][0]['p'] = -np.eye(6)
    refused_after(tmp_path, indefinite, 'estimator.p is not positive definite')

    def asymmetric(sections):
        p = np.eye(6)
        p[0, 1] = 0.5
        sections['estimator'][0]['p'] = p
    refused_after(tmp_path, asymmetric, 'estimator.p is not symmetric')


def test_a_boolean_or_text_for_a_number_is_refused(tmp_path):
    def text(sections):
        sections['feeder'][1]['used'] = '300'
    refused_after(tmp_path, text, 'feeder.used is .300., expected a number')


@pytest.mark.parametrize('version', [True, 0, -1, 1.0, '1'])
def test_a_version_that_is_not_a_version_number_is_refused(saved, monkeypatch, version):
    path, fingerprint = saved
    monkeypatch.setattr(persistence, 'VERSION', version)
    settings = settings_of('ding_miso')
    feeder = feeder_of(settings)
    persistence.save_state(path, fingerprint, persistence.identifier_sections(
        feeder.estimator, feeder))
    monkeypatch.undo()
    with pytest.raises(persistence.StateRefused, match='not a version number'):
        persistence.load_state(path, fingerprint)


@pytest.mark.parametrize('scenario,estimator', [
    ('ding_miso', 'rls'), ('ding_miso', 'bcrls'), ('ikenoue_colored', 'bciv'),
    ('ding_miso', 'rpem'), ('ikeda_closed_loop', 'cl_bcls')])
@pytest.mark.parametrize('count', [0, 3, 40, 2000])
def test_genuine_states_pass_the_value_checks(tmp_path, scenario, estimator, count):
    # NaN as "not computed yet" in a young state, huge covariances early on: all genuine
    settings, sections = saved_sections(estimator, count, scenario)
    path = tmp_path / 'genuine.npz'
    persistence.save_state(path, persistence.configuration_fingerprint(settings), sections)
    assert restore(settings, path).used == count


# ------------------------------------------------------------------ files (SPEC §18)
def test_set_aside_keeps_the_refused_file_under_a_new_name(saved):
    path, _ = saved
    original = path.read_bytes()
    first = persistence.set_aside(path)
    assert not path.exists() and first.read_bytes() == original
    assert first.name.startswith('state.npz.rejected-20') and first.name.endswith('Z')
    path.write_bytes(b'another refused file')
    second = persistence.set_aside(path)   # the same second: a new name, nothing replaced
    assert second != first and first.read_bytes() == original


def test_leftover_temporary_files_are_removed(saved):
    path, _ = saved
    leftover = path.parent / f'.{path.name}.abc123.tmp'
    leftover.write_bytes(b'half a state')
    other = path.parent / '.other.npz.abc123.tmp'
    other.write_bytes(b'not ours')
    assert persistence.remove_leftovers(path) == [leftover]
    assert not leftover.exists() and other.exists() and path.exists()


def test_a_second_process_cannot_take_the_lock(tmp_path):
    import subprocess
    import sys

    path = tmp_path / 'state.npz'
    holder = subprocess.Popen(
        [sys.executable, '-c', 'import sys, time\n'
         'from bcid_ros.identifier.persistence import StateLock\n'
         f'lock = StateLock({str(path)!r})\nprint("locked", flush=True)\ntime.sleep(60)'],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == 'locked'
        with pytest.raises(persistence.StateInUse,
                           match=f'in use by another process \\(pid {holder.pid}'):
            persistence.StateLock(path)
    finally:
        holder.kill()
        holder.wait()
    # the kernel dropped the killed holder's lock
    lock = persistence.StateLock(path)
    lock.release()
