"""Random draws by inversion (mbcapture.sensor.sampling): exact laws, and noise that moves little
when the signal moves little (the portability of the noisy golden images rests on it).

Exactness is checked against scipy's own quantile functions (a deterministic, element-wise
comparison, including u a relative 1e-9 either side of every CDF step) and statistically:
mean and variance (5 standard errors of the sample statistics), the pmf at low counts (a
chi-square goodness-of-fit test at the 1e-4 level) and the far tails (binomial standard error
of the observed frequency).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import special, stats

from mbcapture.sensor import SensorConfig, simulate_reads
from mbcapture.sensor.sampling import (
    NoiseStreams,
    binomial_quantile,
    poisson_pmf,
    poisson_quantile,
)

N_SIGMA = 5.0


def _u_with_steps(cdf_steps: np.ndarray, rng: np.random.Generator, n_random: int) -> np.ndarray:
    """Random u plus u a relative 1e-9 below and above every CDF step (the hard cases)."""
    steps = cdf_steps[(cdf_steps > 1e-12) & (cdf_steps < 1 - 1e-12)]
    u = np.concatenate([rng.random(n_random), steps * (1 - 1e-9), steps * (1 + 1e-9)])
    return u[(u > 0) & (u < 1)]


@pytest.mark.parametrize("lam", [1e-6, 0.03, 0.7, 3.0, 7.99, 8.0, 30.0, 411.5, 9_999.0, 2.5e5, 1e6])
def test_poisson_quantile_equals_scipy_ppf(lam):
    rng = np.random.default_rng(int(lam * 1000) % 2**32)
    ks = np.arange(max(0, int(lam - 12 * np.sqrt(lam)) - 3), int(lam + 12 * np.sqrt(lam)) + 12)
    u = _u_with_steps(stats.poisson.cdf(ks, lam), rng, 2000)
    np.testing.assert_array_equal(poisson_quantile(u, lam), stats.poisson.ppf(u, lam))


@pytest.mark.parametrize("n,p", [(1, 0.5), (7, 0.999), (10_000, 1e-4), (10_000, 0.3), (100_000, 1e-3), (40_000, 0.9)])
def test_binomial_quantile_equals_scipy_ppf(n, p):
    rng = np.random.default_rng(n)
    mean, sd = n * p, np.sqrt(n * p * (1 - p))
    ks = np.arange(max(0, int(mean - 12 * sd) - 3), min(n, int(mean + 12 * sd) + 12) + 1)
    u = _u_with_steps(stats.binom.cdf(ks, n, p), rng, 2000)
    np.testing.assert_array_equal(binomial_quantile(u, np.full(u.size, n), p), stats.binom.ppf(u, n, p))


def test_binomial_quantile_edge_probabilities_and_zero_trials():
    u = np.array([0.1, 0.5, 0.9])
    np.testing.assert_array_equal(binomial_quantile(u, np.array([5.0, 5.0, 0.0]), 0.0), [0, 0, 0])
    np.testing.assert_array_equal(binomial_quantile(u, np.array([5.0, 6.0, 0.0]), 1.0), [5, 6, 0])


def test_binomial_quantile_with_a_vanishing_probability_is_zero_and_does_not_crash():
    """A transfer inefficiency near the smallest normal float64 (hypothesis found 1.1e-308) made
    scipy's binomial pmf raise OverflowError inside the walk. For n p < 2^-53, P(X >= 1) <= n p is
    below 1 - u for every float64 u < 1, so every count is exactly 0 (scipy's ppf agrees where it
    works); just above that bound the walk still runs and still equals scipy."""
    u = np.array([2.0**-54, 0.25, 0.5, 0.75, 1 - 2.0**-53])
    for p in (1e-300, 2.2250738585072014e-308, 1.1125369292536007e-308, 5e-324):
        for n in (1.0, 1e4, 2.0**40):
            np.testing.assert_array_equal(binomial_quantile(u, np.full(u.size, n), p), 0.0)
    np.testing.assert_array_equal(binomial_quantile(u, np.full(u.size, 1e4), 1e-300), stats.binom.ppf(u, 1e4, 1e-300))
    # n p = 2^-50 > 2^-53: the last u lies above F(0) = (1 - 2^-70)^(2^20) = 1 - 2^-50 (to 1e-31), so
    # its count is 1 (scipy's ppf says 0 there: it loses the tail in 1 - u)
    n, p = 2.0**20, 2.0**-70
    np.testing.assert_array_equal(binomial_quantile(u, np.full(u.size, n), p), [0, 0, 0, 0, 1])
    out = simulate_reads(
        np.full((4, 2, 3, 3), 500.0),
        [(3,), (3, 2)],
        SensorConfig(transfer_inefficiency=1.1125369292536007e-308),
        np.random.SeedSequence(0),
    )
    base = simulate_reads(np.full((4, 2, 3, 3), 500.0), [(3,), (3, 2)], SensorConfig(), np.random.SeedSequence(0))
    np.testing.assert_array_equal(out.reads_dn, base.reads_dn)  # no electron is lost


def test_poisson_pmf_matches_the_direct_formula_and_sums_to_one():
    for lam in (0.2, 3.0, 50.0, 700.0):
        k = np.arange(0, int(lam + 15 * np.sqrt(lam)) + 20, dtype=float)
        direct = np.exp(k * np.log(lam) - lam - special.gammaln(k + 1))
        np.testing.assert_allclose(poisson_pmf(k, lam), direct, rtol=2e-12, atol=0)
        assert poisson_pmf(k, lam).sum() == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("lam", [0.05, 0.8, 4.0, 25.0, 3000.0, 1e5])
def test_poisson_mean_and_variance(lam):
    n = 400_000
    x = poisson_quantile(NoiseStreams(11).uniform("shot", (n,)), lam)
    assert np.all(x == np.rint(x)) and x.min() >= 0
    assert abs(x.mean() - lam) < N_SIGMA * np.sqrt(lam / n)
    # SE of the sample variance: var * sqrt(2 / (n - 1) + excess kurtosis / n), kurtosis 1 / lam
    assert abs(x.var(ddof=1) - lam) < N_SIGMA * lam * np.sqrt(2 / (n - 1) + 1 / (lam * n))


@pytest.mark.parametrize("lam", [0.3, 2.5, 12.0])
def test_poisson_pmf_at_low_counts_chi_square(lam):
    n = 300_000
    x = poisson_quantile(NoiseStreams(5).uniform("shot", (n,)), lam).astype(int)
    top = int(lam + 6 * np.sqrt(lam) + 3)
    observed = np.bincount(np.minimum(x, top), minlength=top + 1)
    expected = n * np.append(stats.poisson.pmf(np.arange(top), lam), stats.poisson.sf(top - 1, lam))
    keep = expected > 5  # chi-square cells need enough expected counts; merge the rest into one
    obs = np.append(observed[keep], observed[~keep].sum())
    exp = np.append(expected[keep], expected[~keep].sum())
    if exp[-1] < 5:
        obs, exp = obs[:-1], exp[:-1]
        exp *= obs.sum() / exp.sum()
    assert stats.chisquare(obs, exp).pvalue > 1e-4


@pytest.mark.parametrize("lam,z", [(2000.0, 4.0), (2000.0, -4.0), (9.0, 3.5)])
def test_poisson_tails(lam, z):
    """Frequency beyond lam + z sd against the exact tail, within 5 binomial standard errors."""
    n = 2_000_000
    x = poisson_quantile(NoiseStreams(23).uniform("shot", (n,)), lam)
    k = np.floor(lam + z * np.sqrt(lam))
    p = stats.poisson.sf(k, lam) if z > 0 else stats.poisson.cdf(k, lam)
    freq = np.mean(x > k) if z > 0 else np.mean(x <= k)
    assert abs(freq - p) < N_SIGMA * np.sqrt(p * (1 - p) / n)
    assert p * n > 50  # the tail is actually sampled


def test_a_tiny_change_of_the_mean_changes_few_draws_by_one():
    """The property the cross-CPU goldens need: means perturbed by a relative 1e-7 (what another
    vector width does to a render) change a draw only where a CDF step lies between them."""
    rng = np.random.default_rng(0)
    lam = rng.uniform(0.1, 20_000.0, 400_000)
    u = NoiseStreams(1).uniform("shot", lam.shape)
    a = poisson_quantile(u, lam)
    b = poisson_quantile(u, lam * (1 + 1e-7))
    diff = b - a
    assert set(np.unique(diff)) <= {0.0, 1.0}
    # a draw moves up by one exactly when u falls between F(k; lam (1 + d)) and F(k; lam); as
    # dF(k)/dlam = -pmf(k), that has probability sum_k pmf(k) d lam = d lam: here ~1e-3 on average
    p = 1e-7 * lam
    assert abs(np.mean(diff) - p.mean()) < N_SIGMA * np.sqrt(np.sum(p * (1 - p))) / lam.size
    # numpy's rejection sampler, for contrast, reshuffles nearly every draw
    c = np.random.default_rng(3).poisson(lam)
    d = np.random.default_rng(3).poisson(lam * (1 + 1e-7))
    assert np.mean(c != d) > 0.1  # measured: 21 %, against 0.1 % here


def test_noise_streams_are_fixed_by_seed_and_stage_and_independent_of_each_other():
    s1, s2 = NoiseStreams(np.random.SeedSequence(9)), NoiseStreams(np.random.SeedSequence(9))
    np.testing.assert_array_equal(s1.uniform("shot", (5, 7)), s2.uniform("shot", (5, 7)))
    np.testing.assert_array_equal(s1.uniform("shot", (5, 7)), s1.uniform("shot", (5, 7)))
    assert not np.array_equal(s1.uniform("shot", (5, 7)), s1.uniform("transfer", (5, 7)))
    u = s1.uniform("shot", (100_000,))
    assert u.min() > 0 and u.max() < 1
    with pytest.raises(ValueError, match="noise stage"):
        s1.uniform("nope", (2,))


def test_turning_one_noise_source_on_leaves_the_others_draws_unchanged():
    """Transfer inefficiency on: the shot-noise electrons are identical, and with zero loss
    so are the reads; read noise doubled: the same photons, the read noise exactly doubled."""
    exp_e = np.full((4, 8, 16, 3), 800.0)
    reads = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]
    base = SensorConfig(prnu=0.0, dsnu_e=0.0)
    a = simulate_reads(exp_e, reads, base, np.random.SeedSequence(4))
    b = simulate_reads(exp_e, reads, base.model_copy(update={"transfer_inefficiency": 1e-3}), np.random.SeedSequence(4))
    np.testing.assert_array_equal(a.electrons, b.electrons)
    assert np.all(b.reads_dn <= a.reads_dn + 1) and np.any(b.reads_dn < a.reads_dn)
    c = simulate_reads(
        exp_e,
        reads,
        base.model_copy(update={"read_noise_e": 2 * base.read_noise_e, "gain_dn_per_e": 1.0, "black_level_dn": 0.0}),
        np.random.SeedSequence(4),
    )
    d = simulate_reads(
        exp_e, reads, base.model_copy(update={"gain_dn_per_e": 1.0, "black_level_dn": 0.0}), np.random.SeedSequence(4)
    )
    np.testing.assert_array_equal(c.electrons, d.electrons)
    fd = np.stack([a.electrons[list(r)].sum(axis=0) for r in reads])
    # DN = rint(fd + noise): the noise of c is twice that of d, up to the rounding of each
    np.testing.assert_allclose(c.reads_dn - fd, 2 * (d.reads_dn - fd), atol=1.5)


def test_binomial_with_a_subnormal_probability_is_exact_and_finite():
    """p = 2e-307 (found by the property test of the sensor): P(X > 0) <= n p is far below the
    uniforms' 2^-53 grid, so every draw is 0 (scipy's beta functions overflow there)."""
    u = np.array([1e-9, 0.5, 1 - 2.0**-53])
    np.testing.assert_array_equal(binomial_quantile(u, np.full(3, 1558.0), 2.17e-307), [0, 0, 0])
    np.testing.assert_array_equal(binomial_quantile(u, np.full(3, 10.0), 1 - 1e-300), [10, 10, 10])


def test_uniform_open_moves_an_exact_zero_inside_the_interval_and_keeps_shapes():
    """rng.random returns 0 with probability 2^-53, too rare to meet by sampling: a stand-in
    generator returns it. 0 becomes 2^-54 (so that inverse CDFs never see u = 0); nothing else
    moves. Binomial draws keep the shape of their input at p = 0 and p = 1 too."""
    from mbcapture.sensor.sampling import uniform_open

    class Zeros:
        def random(self, shape):
            return np.array([[0.0, 0.25], [0.5, 1 - 2.0**-53]]).reshape(shape)

    u = uniform_open(Zeros(), (2, 2))
    np.testing.assert_array_equal(u, [[2.0**-54, 0.25], [0.5, 1 - 2.0**-53]])
    assert poisson_quantile(u, 3.0)[0, 0] == 0.0
    uu, n = np.full((2, 3), 0.5), np.full((2, 3), 7.0)
    assert binomial_quantile(uu, n, 0.0).shape == (2, 3) and binomial_quantile(uu, n, 1.0).shape == (2, 3)
    np.testing.assert_array_equal(binomial_quantile(uu, n, 1.0), n)


@pytest.mark.parametrize("offset", [-40, -7, -1, 0, 1, 7, 40])
def test_invert_discrete_finds_the_quantile_from_any_start(offset):
    """The inversion is exact whatever its start: walking down from above, up from below, far
    (40 counts: several re-walks) or near, for Poisson lanes (unbounded) and binomial lanes (bounded
    by n, starts beyond n clipped). Against scipy's ppf, u including a relative 1e-9 either side of
    every CDF step. The samplers themselves start within a count or two, so only this exercises
    the long walks."""
    from mbcapture.sensor.sampling import DiscreteLaw, invert_discrete

    rng = np.random.default_rng(abs(offset) + 100)
    for lam in (0.7, 30.0, 5000.0):
        ks = np.arange(0, int(lam + 10 * np.sqrt(lam)) + 10)
        u = _u_with_steps(stats.poisson.cdf(ks, lam), rng, 300)
        want = stats.poisson.ppf(u, lam)
        got = invert_discrete(u, np.maximum(want + offset, 0.0), DiscreteLaw("poisson", np.full(u.size, lam)))
        np.testing.assert_array_equal(got, want, err_msg=f"Poisson {lam}, start offset {offset}")
    for n, p in ((12, 0.4), (2000, 0.03)):
        ks = np.arange(0, n + 1)
        u = _u_with_steps(stats.binom.cdf(ks, n, p), rng, 300)
        want = stats.binom.ppf(u, n, p)
        got = invert_discrete(u, np.maximum(want + offset, 0.0), DiscreteLaw("binomial", np.full(u.size, float(n)), p))
        np.testing.assert_array_equal(got, want, err_msg=f"binomial {n}, {p}, start offset {offset}")


def test_noise_streams_from_an_int_or_a_generator_are_reproducible():
    np.testing.assert_array_equal(NoiseStreams(5).uniform("shot", (4,)), NoiseStreams(5).uniform("shot", (4,)))
    assert not np.array_equal(NoiseStreams(5).uniform("shot", (4,)), NoiseStreams(6).uniform("shot", (4,)))
    a = NoiseStreams(np.random.default_rng(8)).normal("read", (4,))
    np.testing.assert_array_equal(a, NoiseStreams(np.random.default_rng(8)).normal("read", (4,)))
    assert not np.array_equal(a, NoiseStreams(np.random.default_rng(9)).normal("read", (4,)))


def test_poisson_memo_returns_the_same_draw_and_only_for_the_same_field_and_means(monkeypatch):
    """A repeat of a draw (same uniform field, same means) comes from the memo, equal to the exact
    inversion and a fresh array; another field or a mean one ulp away is drawn again."""
    from mbcapture.sensor.sampling import POISSON_MEMO, poisson_quantile_memo

    monkeypatch.setattr(POISSON_MEMO, "entries", 4)  # on, as in a sweep's workers
    POISSON_MEMO.clear()
    u = NoiseStreams(3).uniform("shot", (2, 5, 7))
    lam = np.linspace(0.5, 4000.0, u.size).reshape(u.shape)
    first = poisson_quantile_memo(u, lam)
    np.testing.assert_array_equal(first, poisson_quantile(u, lam))
    first[...] = -1  # the caller's array, not the memo's
    again = poisson_quantile_memo(u, lam)
    np.testing.assert_array_equal(again, poisson_quantile(u, lam))
    assert (POISSON_MEMO.hits, POISSON_MEMO.misses) == (1, 1)
    poisson_quantile_memo(NoiseStreams(4).uniform("shot", u.shape), lam)
    poisson_quantile_memo(u, np.nextafter(lam, np.inf))
    assert (POISSON_MEMO.hits, POISSON_MEMO.misses) == (1, 3)
    for i in range(POISSON_MEMO.entries + 1):  # the oldest entries make room
        poisson_quantile_memo(u, lam + i + 1)
    poisson_quantile_memo(u, lam)
    assert POISSON_MEMO.misses == 3 + POISSON_MEMO.entries + 2


def test_a_sweeps_memos_give_the_same_reads_and_share_the_fields(monkeypatch):
    """With the memos on (a sweep's process), the sensor gives the same reads bit for bit as without
    them; a second point of the same sensor seed takes its noise fields, fixed pattern and photons from
    them (hits), read-only; a sensor with another PRNU draws its own maps, another noise seed its own fields."""
    from mbcapture.sensor.readout import fixed_pattern
    from mbcapture.sensor.sampling import FIELD_MEMO, POISSON_MEMO

    cfg = SensorConfig(
        prnu=0.01, dsnu_e=2.0, read_noise_e=3.0, read_noise_row_e=0.5, transfer_inefficiency=1e-4, full_well_e=5000.0
    )
    exp_e = np.random.default_rng(0).uniform(0.0, 6000.0, (3, 6, 7, 3))
    reads = [(0,), (0, 1), (0, 1, 2)]

    def sense(c=cfg, seed=11):
        return simulate_reads(exp_e, reads, c, np.random.SeedSequence(seed))

    off = sense()
    for memo, n in ((FIELD_MEMO, 8), (POISSON_MEMO, 4)):
        monkeypatch.setattr(memo, "entries", n)
        memo.clear()
    first = sense()
    hits = FIELD_MEMO.hits
    second = sense(cfg.model_copy(update={"read_noise_e": 6.0}))  # another point of a read-noise sweep
    # shot and transfer uniforms, read and row normals, the fixed pattern; and the photons
    assert FIELD_MEMO.hits - hits == 5 and POISSON_MEMO.hits == 1
    for a, b in ((off, first), (first, second)):
        np.testing.assert_array_equal(a.electrons, b.electrons)
    np.testing.assert_array_equal(off.reads_dn, first.reads_dn)
    assert not np.array_equal(first.reads_dn, second.reads_dn)  # its own read noise on the same field
    np.testing.assert_array_equal(
        second.reads_dn,
        simulate_reads(exp_e, reads, cfg.model_copy(update={"read_noise_e": 6.0}), np.random.SeedSequence(11)).reads_dn,
    )
    streams = NoiseStreams(np.random.SeedSequence(11))
    u = streams.uniform("shot", exp_e.shape)
    with pytest.raises(ValueError):
        u[0, 0, 0, 0] = 0.5  # the memo's array is handed out read-only
    np.testing.assert_array_equal(
        np.stack([r.copy() for r in streams.normal_runs("read", (3, 6, 7, 3))]), streams.normal("read", (3, 6, 7, 3))
    )
    misses = FIELD_MEMO.misses
    fixed_pattern((6, 7, 3), cfg.model_copy(update={"prnu": 0.02}))
    sense(seed=12)  # its four noise fields anew; the fixed pattern is the sensor's (sensor.fpn_seed), the same
    assert FIELD_MEMO.misses - misses == 1 + 4


@pytest.mark.parametrize("law", ["poisson", "binomial"])
def test_inverting_in_chunks_gives_the_same_counts(monkeypatch, law):
    """The inversion is per lane: chunks of 7 lanes (CHUNK_LANES) give the counts of one pass, bit for
    bit, on means from 0 to beyond the exact range, both tails, and u at its extremes."""
    import mbcapture.sensor.sampling as sampling

    rng = np.random.default_rng(11)
    mean = np.concatenate([[0.0, 1e-9, 0.3, 5.0, 1e3, 2.0**51], rng.uniform(0, 50, 200), 10 ** rng.uniform(-2, 7, 198)])
    u = np.concatenate([[1e-300, 0.5, 1 - 2**-53, 1e-17, 0.999999, 0.3], rng.random(398)])
    shape = (4, 101)  # not a multiple of the chunk
    mean, u = mean.reshape(shape), u.reshape(shape)
    if law == "poisson":
        whole = sampling.poisson_quantile(u, mean)
        monkeypatch.setattr(sampling, "CHUNK_LANES", 7)
        chunked = sampling.poisson_quantile(u, mean)
    else:
        n = np.floor(np.minimum(mean, 1e6))
        whole = sampling.binomial_quantile(u, n, 0.013)
        monkeypatch.setattr(sampling, "CHUNK_LANES", 7)
        chunked = sampling.binomial_quantile(u, n, 0.013)
    assert chunked.shape == shape and np.array_equal(chunked, whole)


def test_the_inversions_threads_change_nothing_but_time(monkeypatch):
    """Chunks run on a thread pool (sampling.set_threads, or every usable core): 1 or 3 threads give
    the counts of one pass, bit for bit."""
    import mbcapture.sensor.sampling as sampling

    rng = np.random.default_rng(12)
    mean = 10 ** rng.uniform(-2, 6, 5000)
    u = rng.random(5000)
    whole = sampling.poisson_quantile(u, mean)
    monkeypatch.setattr(sampling, "CHUNK_LANES", 256)
    try:
        for n in (1, 3):
            sampling.set_threads(n)
            assert np.array_equal(sampling.poisson_quantile(u, mean), whole)
    finally:
        sampling.set_threads(None)


def test_normal_runs_are_the_fields_leading_slices_bit_for_bit():
    """NoiseStreams.normal_runs yields normal(stage, shape, rows)[i] for each i in order (the whole
    field's values, drawn one slice at a time into one array), for the whole film and for a band."""
    shape = (3, 20, 7, 3)
    whole = NoiseStreams(9).normal("read", shape)
    runs = [r.copy() for r in NoiseStreams(9).normal_runs("read", shape)]
    assert len(runs) == 3
    np.testing.assert_array_equal(np.stack(runs), whole)
    streams = NoiseStreams(9)
    for r0, r1 in ((0, 6), (6, 20)):  # bands in order, as a tiled capture asks
        band = np.stack([r.copy() for r in streams.normal_runs("read", shape, (r0, r1))])
        np.testing.assert_array_equal(band, whole[:, r0:r1])
    assert not np.array_equal(np.stack(runs), NoiseStreams(10).normal("read", shape))


def test_the_poisson_start_is_the_general_cornish_fisher_start_with_poissons_moments():
    """_poisson_start is _start's expansion reduced for skewness 1/sd and excess kurtosis 1/lam: the
    same integer starts (both sides of the variance below which the plain normal quantile is used),
    so the walks stay as short as they were. A wrong reduction would move the starts by counts."""
    from mbcapture.sensor.sampling import _CF_MIN_VAR, _poisson_start, _start

    rng = np.random.default_rng(7)
    lam = np.concatenate([10.0 ** rng.uniform(-2, 7, 200_000), [_CF_MIN_VAR * (1 - 1e-12), _CF_MIN_VAR]])
    z = special.ndtri(rng.uniform(1e-9, 1 - 1e-9, lam.size))
    general = _start(z, lam, lam, 1.0 / np.sqrt(lam), 1.0 / lam)
    fast = _poisson_start(z, lam)
    # the two orders of the same arithmetic may round across a half-integer: at most one count, rarely
    assert np.abs(fast - general).max() <= 1.0
    assert np.count_nonzero(fast != general) <= lam.size * 1e-5


@pytest.mark.parametrize("n, p", [(14_057_673, 0.3), (10**9, 1e-3), (2_000_000, 0.5)])
def test_binomial_quantile_is_exact_where_the_variance_is_large(n, p):
    """Variances of 1e5 to 3.5e6 (a full well of millions of electrons with a large transfer loss): the tails come
    from betainc there (bdtr's error reached 2.4 pmfs at a variance of 1e6, and the walks never settled). Against
    scipy.stats.binom.ppf (Boost), u including a relative 1e-9 either side of CDF steps near the mean."""
    rng = np.random.default_rng(11)
    sd = np.sqrt(n * p * (1 - p))
    ks = np.floor(n * p + sd * np.linspace(-4, 4, 41))
    u = _u_with_steps(stats.binom.cdf(ks, n, p), rng, 400)
    np.testing.assert_array_equal(binomial_quantile(u, np.full(u.size, float(n)), p), stats.binom.ppf(u, n, p))
