"""
The measurements of bench/speed.py: the library's costs and the node's message path.

``bench_core`` times fit, update, prediction and certification of the D-GP models against
scikit-learn's GaussianProcessRegressor and the Cholesky floor at each buffer size;
``bench_node`` times the estimator's message path (``OnlineEstimator.process``) per buffer size,
with a profile of its top functions. What they measure and why: bench/speed.py's docstring.
"""
from __future__ import annotations

import cProfile
import io
import os
import pstats
import sys
import time

import numpy as np

import common as C
N_OUT = 3
K_BATCH = 2000          # test points per batch prediction


# ----------------------------------------------------------------------------- data
def make_model(kind, **kw):
    """
    ``dgp_ros.gp.make_model`` with passivity 'none' unless given.

    The exact-fit, update and prediction numbers here are the numerics against the Cholesky
    floor and scikit-learn, as measured before ``certified`` became the library default; the
    node section passes its passivity mode explicitly.
    """
    from dgp_ros.gp import make_model as _make
    return _make(kind, **{'passivity': 'none', **kw})


def make_data(n_max: int, seed: int = 0):
    """
    Make the benchmark data.

    (alpha, beta, V) uniform in the flown envelope, forces from the frozen-state JSBSim A320,
    plus 1 % noise (so that the noise hyper-parameter is not at its floor).
    """
    from sim_bridge import FrozenAero, SimConfig
    from paper_experiments import VOLUME_HI, VOLUME_LO
    rng = np.random.default_rng(seed)
    aero = FrozenAero(SimConfig())
    Q = C.random_points(rng, VOLUME_LO, VOLUME_HI, n_max + K_BATCH + 50)
    T = aero.tau(Q)
    T = T + 0.01 * T.std(axis=0) * rng.standard_normal(T.shape)
    return Q, T


def sk_models(model, Q, T):
    """One sklearn GPR per output with exactly ``model``'s ARD hyper-parameters (standardized)."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
    hp = model.hyperparams_
    sx, sy = (np.asarray(hp[k]) for k in ('sx', 'sy'))
    mean = model.mean_(np.zeros((1, N_OUT)))[0]           # the constant prior of the ARD baseline
    X = Q / sx
    Y = (T - mean) / sy
    out = []
    for m in range(N_OUT):
        k = (ConstantKernel(np.exp(hp['log_sf2'][m]), constant_value_bounds='fixed') *
             RBF(length_scale=np.exp(np.asarray(hp['log_ls'][m])), length_scale_bounds='fixed') +
             WhiteKernel(np.exp(hp['log_sn2'][m]), noise_level_bounds='fixed'))
        out.append(GaussianProcessRegressor(kernel=k, optimizer=None, alpha=1e-10,
                                            normalize_y=False, copy_X_train=False))
    return out, X, Y, (sx, sy, mean)


def sk_fit(gprs, X, Y):
    for m, g in enumerate(gprs):
        g.fit(X, Y[:, m])


def sk_predict(gprs, Xs, std=False):
    return [g.predict(Xs, return_std=std) for g in gprs]


def floor_matrix(model, n):
    """Return an n x n SPD matrix like the fit's (output 0's kernel + noise), standardized."""
    p = model.posterior_
    X = p.X[:n]
    K = p.structure.output_kernel(0, X, X, p.hyper.log_ls, p.hyper.log_sf2)
    K[np.diag_indices(n)] += np.exp(p.hyper.log_sn2[0])
    return K


def profile_top(fn, k: int = 8) -> str:
    pr = cProfile.Profile()
    pr.enable()
    fn()
    pr.disable()
    s = io.StringIO()
    st = pstats.Stats(pr, stream=s).sort_stats('tottime')
    st.print_stats(k)
    lines = s.getvalue().splitlines()
    # keep the table only (drop the preamble), shorten paths
    i = next((j for j, ln in enumerate(lines) if ln.strip().startswith('ncalls')), 0)
    keep = [ln.replace(C.REPO + '/', '') for ln in lines[i:i + k + 1] if ln.strip()]
    keep = [ln.replace(sys.prefix + '/', '') for ln in keep]
    return '```\n' + '\n'.join(keep) + '\n```\n'


# ----------------------------------------------------------------------------- core bench
def bench_core(a, Q, T, ns):
    from scipy.linalg import cho_factor
    hps, res, opt = {}, {}, {}
    # hyper-parameter optimization timing (ours: 3 starts per output on <= 300 samples); the
    # models optimized on the largest of these n give the hyper-parameters kept for every n
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
    opt_ns = [100] if a.quick else [100, 300]
    nr = 0 if a.quick else 2
    for n in opt_ns:
        for kind in C.KINDS:
            C.log(f'speed: hyper-parameter optimization n={n} {kind}')
            t0 = time.perf_counter()
            m = make_model(kind, n_restarts=nr).fit(Q[:n], T[:n], optimize=True)
            opt[(n, kind)] = time.perf_counter() - t0
            hps[kind] = m.hyperparams_
        # sklearn with its optimizer, same kernel family, same number of starts, same data
        hp = hps['ard']
        X = Q[:n] / np.asarray(hp['sx'])
        Y = (T[:n] - np.asarray(hp['mean']['value'])) / np.asarray(hp['sy'])
        t0 = time.perf_counter()
        for m in range(N_OUT):
            k = ConstantKernel(1.0) * RBF(np.ones(3)) + WhiteKernel(1e-2)
            GaussianProcessRegressor(kernel=k, n_restarts_optimizer=nr,
                                     random_state=0).fit(X, Y[:, m])
        opt[(n, 'sk')] = time.perf_counter() - t0
    Qb = Q[-K_BATCH:]
    for n in ns:
        Qn, Tn = Q[:n], T[:n]
        rep = 5 if n <= 1000 else (3 if n <= 2000 else 2)
        if a.quick:
            rep = 3
        r = res[n] = {}
        for kind in C.KINDS:
            C.log(f'speed n={n} {kind}')
            hp = hps[kind]
            fit = lambda: make_model(kind, hyperparams=hp).fit(Qn, Tn, optimize=False)  # noqa
            r[(kind, 'fit')] = C.timeit(fit, repeat=rep)
            m = fit()
            r[(kind, 'predict_pp')] = C.timeit(lambda: m.predict(Qb), repeat=rep) / K_BATCH
            if n <= 2000:
                r[(kind, 'predict_var_pp')] = C.timeit(
                    lambda: m.predict(Qb, return_var=True), repeat=rep) / K_BATCH
            q1 = Qb[:1]
            r[(kind, 'single')] = C.timeit(lambda: m.predict(q1), repeat=7, min_time=0.05)
            if kind != 'ard':
                def node_path():
                    m.predict(q1, return_var=True)
                    m.damping_matrix(q1)
            else:
                def node_path():
                    m.predict(q1, return_var=True)
            r[(kind, 'single_node')] = C.timeit(node_path, repeat=7, min_time=0.05)
            # one-sample update, growing (no window): fresh model, a few consecutive updates
            k_up = 5 if n >= 2000 else 10

            def updates(mu):
                ts = []
                for i in range(k_up):
                    t0 = time.perf_counter()
                    mu.update(Q[n + i], T[n + i])
                    ts.append(time.perf_counter() - t0)
                return float(np.median(ts))
            r[(kind, 'update')] = updates(fit())
            # windowed update at steady state (the node's buffer): drops the oldest sample
            r[(kind, 'update_window')] = updates(
                make_model(kind, hyperparams=hp, window=n).fit(Qn, Tn, optimize=False))
            if kind == 'ard':
                ard = m
        # floor: N x cho_factor of an n x n SPD matrix
        A = floor_matrix(ard, n)
        r['floor'] = C.timeit(lambda: [cho_factor(A, lower=True, check_finite=False)
                                       for _ in range(N_OUT)], repeat=rep)
        # scikit-learn, same kernel and data (ARD)
        # the lambdas run before the ``del gprs`` below (pyflakes cannot see that): noqa F821
        gprs, X, Y, (sx, sy, mean) = sk_models(ard, Qn, Tn)
        r['sk_fit'] = C.timeit(lambda: sk_fit(gprs, X, Y), repeat=rep)  # noqa: F821
        Xb = Qb / sx
        r['sk_predict_pp'] = C.timeit(lambda: sk_predict(gprs, Xb),  # noqa: F821
                                      repeat=rep) / K_BATCH
        if n <= 2000:
            r['sk_predict_var_pp'] = C.timeit(lambda: sk_predict(gprs, Xb, True),  # noqa: F821
                                              repeat=rep) / K_BATCH
        x1 = Xb[:1]
        r['sk_single'] = C.timeit(lambda: sk_predict(gprs, x1),  # noqa: F821
                                  repeat=7, min_time=0.05)
        # agreement check: same model, same numbers
        ours = ard.predict(Qb)
        sk = np.column_stack(sk_predict(gprs, Xb)) * sy + mean
        r['sk_agree'] = float(np.max(np.abs(ours - sk) / (np.abs(sk).max(axis=0) + 1e-300)))
        del gprs
    return res, opt, hps


# ----------------------------------------------------------------------------- node
def bench_node(a, buffers, n_msgs, tmpdir):
    """
    Drive ``OnlineEstimator.process`` in-process.

    Warm start through the node's documented model-file path: a model fitted on ``b`` samples of
    the approach (hyper-parameters optimized once, window = b) is saved and the estimator loads it
    (its training set becomes the buffer), so the timed messages are all steady state. Then
    ``n_msgs`` messages are processed back to back with every sample added (selection 'all': the
    windowed O(n^2) update on every message, the worst case) and no refits. The 'default' row
    keeps the config defaults (projected, buffer 200, novelty selection, async refits every 10 s
    of stamp time) and calls ``diagnostics()`` once per wall second on the message thread, as the
    node's timer does.
    """
    from sim_bridge import SimConfig, simulate_approach
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    data = simulate_approach(SimConfig())
    Qd, Td = data['q'], data['tau']
    names = list(data['joint_names'])
    rng = np.random.default_rng(3)
    out = {}

    def stream(est, n, t_start, diag_every_s=None, stamp_hz=60.0):
        lat = np.empty(n)
        diag_t = []
        k = Qd.shape[0]
        t_wall = time.perf_counter()
        next_diag = t_wall + (diag_every_s or np.inf)
        for i in range(n):
            j = (t_start + i) % k
            # jitter so that a looped trajectory keeps adding novel samples
            q = Qd[j] * (1.0 + 1e-3 * rng.standard_normal(3))
            t0 = time.perf_counter()
            est.process((t_start + i) / stamp_hz, names, q, Td[j])
            t1 = time.perf_counter()
            lat[i] = t1 - t0
            if t1 >= next_diag:
                est.diagnostics()
                t2 = time.perf_counter()
                diag_t.append(t2 - t1)
                next_diag = t2 + diag_every_s
        wall = time.perf_counter() - t_wall
        return lat, wall, diag_t

    hp = {}
    sub = np.linspace(0, Qd.shape[0] - 1, 200).astype(int)

    def model_file(kind, mode, b):
        if kind not in hp:
            C.log(f'node: optimizing {kind} hyper-parameters on 200 approach samples')
            hp[kind] = make_model(kind, n_restarts=0, max_opt_samples=200).fit(
                Qd[sub], Td[sub]).hyperparams_
        idx = np.linspace(0, Qd.shape[0] - 1, b).astype(int)
        t0 = time.perf_counter()
        m = make_model(kind, passivity=mode, hyperparams=hp[kind], window=b).fit(
            Qd[idx], Td[idx], optimize=False)
        fit_s = time.perf_counter() - t0
        path = os.path.join(tmpdir, f'node_{kind}_{mode}_{b}.npz')
        m.save(path)
        return path, fit_s, m.certificate()

    def row(n, wall, lat, d, **extra):
        """One table row: rate, latency percentiles and the invariant counters."""
        return dict(rate=n / wall, p50=np.percentile(lat, 50), p99=np.percentile(lat, 99),
                    max=lat.max(), fallbacks=d['passivity_fallbacks'], trained=d['trained'],
                    lat=lat, **extra)

    def worst_case_cfg(kind, mode, b, **kw):
        """Warm-started from the model file, every sample learned, no refits."""
        base = {'model': kind, 'passivity': mode, 'buffer_size': b, 'min_samples': 20,
                'refit_period_s': 0.0, 'selection': 'all', 'refit_mode': 'sync',
                'model_path': files[(kind, mode, b)], 'min_sample_interval_s': 0.0}
        base.update(kw)
        return EstimatorConfig(**base)

    scen = [('full', 'projected', b) for b in buffers]
    if not a.quick:
        scen += [('full', 'none', 500), ('diag', 'projected', 500), ('ard', 'projected', 500),
                 ('full', 'certified', 200)]
    files = {}
    for kind, mode, b in scen:
        path, fit_s, cert = model_file(kind, mode, b)
        files[(kind, mode, b)] = path
        C.log(f'node: {kind} {mode} buffer {b} (warm-start fit {fit_s:.1f} s, {cert.method})')
        # paper/certified: a stale certificate (after update) is re-proved by a refit; the
        # node does that in a background thread ('async'), never on the message path
        rmode = 'async' if mode in ('paper', 'certified') else 'sync'
        est = OnlineEstimator(worst_case_cfg(kind, mode, b, refit_mode=rmode))
        assert est.trained and not est.load_error, est.load_error
        stream(est, 50, 0)                                  # warm-up (caches, first names)
        lat, wall, _ = stream(est, n_msgs, 50)
        d = est.diagnostics()
        out[(kind, mode, 'all', b)] = row(n_msgs, wall, lat, d, fit_s=fit_s,
                                          note=(f'async re-proofs: {d["refits_ok"]} ok, '
                                                f'{d["refits_failed"]} failed'
                                                if rmode == 'async' else ''))
        est.close()
    # a 1 kHz stream (1 ms stamps) with the default learning limit (min_sample_interval_s =
    # 0.01: every message answered, one in ten learned), the other settings as above
    b1 = 500 if 500 in buffers else buffers[-1]
    est = OnlineEstimator(worst_case_cfg('full', 'projected', b1,
                                         min_sample_interval_s=EstimatorConfig().
                                         min_sample_interval_s))
    stream(est, 50, 0, stamp_hz=1000.0)
    lat, wall, _ = stream(est, n_msgs, 50, stamp_hz=1000.0)
    d = est.diagnostics()
    out[('full', 'projected', '1 kHz, learn <= 100 Hz', b1)] = row(
        n_msgs, wall, lat, d, fit_s=None,
        note=f'{d["samples_rate_limited"]} rate-limited, {d["samples_added"]} added')
    est.close()
    if not a.quick:
        b = 200
        C.log('node: default config (projected, novelty, async refit every 10 s stamp time)')
        cfg = EstimatorConfig(buffer_size=b, refit_mode='async',
                              model_path=files[('full', 'projected', 200)])
        est = OnlineEstimator(cfg)
        n2 = max(n_msgs, 3000)
        lat, wall, diag_t = stream(est, n2, 0, diag_every_s=1.0)
        d = est.diagnostics()
        est.wait_for_refit(120)
        d2 = est.diagnostics()
        out[('default', cfg.passivity, 'novelty', b)] = row(
            n2, wall, lat, d, fit_s=d2['last_refit_duration_s'], diag=diag_t,
            refits=d2['refits_ok'],
            refits_started=d2['refits_ok'] + d2['refits_failed'],
            skipped=d['samples_skipped'], added=d['samples_added'])
        est.close()
    # profile the message path at buffer 500 (or the largest quick buffer)
    est = OnlineEstimator(worst_case_cfg('full', 'projected', b1))
    prof = profile_top(lambda: stream(est, 200 if a.quick else 1000, 0), 10)
    est.close()
    return out, prof
