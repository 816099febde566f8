"""The standards' figures against worked examples computed here by plain loops (not by the
module), and against the Gaussian predictions of their statistics."""
import json
import math

import numpy as np
import pytest

from deltatwin.calibration.standards import iso230_2, iso230_3, iso9283
from deltatwin.calibration.standards.gaussian import c4, r_gaussian, rp_gaussian

UM = 1e-6

# ISO 230-2 worked example: 4 targets, 5 approaches each way, deviations in um. Target 2 has
# the largest reversal, target 3 the largest scatter down, so that the axis values come from
# different targets.
TARGETS_230_2 = [0.0, 2.5e-3, 5.0e-3, 7.5e-3]
UP = [[1.2, 1.5, 1.1, 1.4, 1.3],
      [2.0, 2.4, 2.1, 2.2, 2.3],
      [-0.5, -0.2, -0.4, -0.1, -0.3],
      [0.6, 0.9, 0.7, 0.8, 1.0]]
DOWN = [[0.9, 1.0, 0.7, 1.1, 0.8],
        [0.1, 0.3, -0.1, 0.2, 0.0],
        [-1.0, -0.3, -0.8, -0.2, -0.6],
        [0.4, 0.5, 0.2, 0.6, 0.3]]


def hand_230_2(up, down):
    """ISO 230-2 by plain loops (lists of lists, um)."""
    def mean(v):
        total = 0.0
        for x in v:
            total += x
        return total / len(v)

    def sdev(v):
        m = mean(v)
        total = 0.0
        for x in v:
            total += (x - m) ** 2
        return math.sqrt(total / (len(v) - 1))

    out = {k: [] for k in ("xu", "xd", "x", "B_i", "su", "sd", "Ru_i", "Rd_i", "R_i")}
    for u, d in zip(up, down):
        xu, xd, su, sd = mean(u), mean(d), sdev(u), sdev(d)
        b = xu - xd
        out["xu"].append(xu)
        out["xd"].append(xd)
        out["x"].append((xu + xd) / 2)
        out["B_i"].append(b)
        out["su"].append(su)
        out["sd"].append(sd)
        out["Ru_i"].append(4 * su)
        out["Rd_i"].append(4 * sd)
        out["R_i"].append(max(2 * su + 2 * sd + abs(b), 4 * su, 4 * sd))
    ax = {"B": max(abs(b) for b in out["B_i"]), "B_mean": mean(out["B_i"]),
          "R_up": max(out["Ru_i"]), "R_down": max(out["Rd_i"]), "R": max(out["R_i"]),
          "E_up": max(out["xu"]) - min(out["xu"]), "E_down": max(out["xd"]) - min(out["xd"]),
          "E": max(out["xu"] + out["xd"]) - min(out["xu"] + out["xd"]),
          "M": max(out["x"]) - min(out["x"])}
    hi_u = [x + 2 * s for x, s in zip(out["xu"], out["su"])]
    lo_u = [x - 2 * s for x, s in zip(out["xu"], out["su"])]
    hi_d = [x + 2 * s for x, s in zip(out["xd"], out["sd"])]
    lo_d = [x - 2 * s for x, s in zip(out["xd"], out["sd"])]
    ax.update(A_up=max(hi_u) - min(lo_u), A_down=max(hi_d) - min(lo_d),
              A=max(hi_u + hi_d) - min(lo_u + lo_d))
    return out, ax


def test_iso230_2_worked_example_agrees_with_plain_loops():
    r = iso230_2.evaluate(TARGETS_230_2, np.array(UP) * UM, np.array(DOWN) * UM, "x")
    per, ax = hand_230_2(UP, DOWN)
    names = {"xu": "xbar_up", "xd": "xbar_down", "x": "xbar", "B_i": "B_i", "su": "s_up",
             "sd": "s_down", "Ru_i": "R_up_i", "Rd_i": "R_down_i", "R_i": "R_i"}
    for k, attr in names.items():
        np.testing.assert_allclose(getattr(r, attr) / UM, per[k], rtol=0, atol=1e-12)
    for k, v in ax.items():
        assert abs(getattr(r, k) / UM - v) <= 1e-12, k
    # the bidirectional R comes from 2s+2s+|B| at target 2 here, not from a 4s
    i = int(np.argmax(per["R_i"]))
    assert per["R_i"][i] == pytest.approx(2 * per["su"][i] + 2 * per["sd"][i] + abs(per["B_i"][i]))
    assert r.R > max(r.R_up, r.R_down)


def test_iso230_2_axis_values_never_below_a_per_target_value():
    rng = np.random.default_rng(7)
    for _ in range(200):
        m, n = rng.integers(2, 8), rng.integers(2, 7)
        up = rng.normal(rng.normal(0, 1, (m, 1)), rng.uniform(0.01, 1, (m, 1)), (m, n))
        down = rng.normal(rng.normal(0, 1, (m, 1)), rng.uniform(0.01, 1, (m, 1)), (m, n))
        r = iso230_2.evaluate(np.arange(m), up, down)
        assert np.all(r.R >= r.R_i) and np.all(r.R >= r.R_up_i) and np.all(r.R >= r.R_down_i)
        assert np.all(r.R_up >= r.R_up_i) and np.all(r.R_down >= r.R_down_i)
        assert np.all(r.B >= np.abs(r.B_i))
        assert r.A >= max(r.A_up, r.A_down) and r.E >= max(r.E_up, r.E_down)
        assert r.A >= r.R_i.max() - 1e-15 * r.A       # A spans every target's 2s bands


def test_iso230_2_from_readings_and_json():
    up, down = np.array(UP) * UM, np.array(DOWN) * UM
    idx = np.repeat(np.arange(4), 5)
    r1 = iso230_2.from_readings(np.concatenate([idx, idx]), np.r_[np.ones(20), -np.ones(20)],
                                np.concatenate([up.ravel(), down.ravel()]), TARGETS_230_2)
    r2 = iso230_2.evaluate(TARGETS_230_2, up, down)
    assert r1.R == r2.R and r1.A == r2.A
    doc = json.loads(r1.to_json())
    assert doc["axis_figures"]["R_nm"] == pytest.approx(r2.R * 1e9)
    assert "R_i" in r1.summary()


@pytest.mark.parametrize("bad, match", [
    (lambda u: u[:, :1], "at least 2 approaches"),
    (lambda u: np.where(np.arange(5) == 3, np.nan, u), "target 0, approach 3"),
    (lambda u: u[:3], "3 targets"),
])
def test_iso230_2_refuses_bad_tables(bad, match):
    with pytest.raises(ValueError, match=match):
        iso230_2.evaluate(TARGETS_230_2, bad(np.array(UP)), np.array(DOWN))


# ISO 9283 worked example: two poses, six cycles each, attained positions in um.
CMD_9283 = [[0.0, 0.0, 0.0], [1000.0, -500.0, 250.0]]
ATT_9283 = [[[0.3, -0.1, 0.2], [0.5, 0.0, 0.1], [0.2, -0.3, 0.4], [0.4, 0.1, 0.0],
             [0.6, -0.2, 0.3], [0.1, 0.0, 0.2]],
            [[1001.2, -499.1, 250.4], [1000.9, -499.5, 250.9], [1001.6, -499.3, 250.1],
             [1001.0, -498.8, 250.6], [1001.4, -499.6, 250.3], [1000.8, -499.0, 250.8]]]


def hand_9283(cmd, att):
    out = []
    for c, pts in zip(cmd, att):
        n = len(pts)
        bx = sum(p[0] for p in pts) / n
        by = sum(p[1] for p in pts) / n
        bz = sum(p[2] for p in pts) / n
        apx, apy, apz = bx - c[0], by - c[1], bz - c[2]
        ap = math.sqrt(apx ** 2 + apy ** 2 + apz ** 2)
        ls = [math.sqrt((p[0] - bx) ** 2 + (p[1] - by) ** 2 + (p[2] - bz) ** 2) for p in pts]
        lbar = sum(ls) / n
        sl = math.sqrt(sum((v - lbar) ** 2 for v in ls) / (n - 1))
        out.append({"APx": apx, "APy": apy, "APz": apz, "AP": ap, "l_bar": lbar, "S_l": sl,
                    "RP": lbar + 3 * sl})
    return out


def test_iso9283_worked_example_agrees_with_plain_loops():
    r = iso9283.evaluate(np.array(CMD_9283) * UM, np.array(ATT_9283) * UM)
    for pose, hand in zip(r.poses, hand_9283(CMD_9283, ATT_9283)):
        for k, v in hand.items():
            assert abs(getattr(pose, k) / UM - v) <= 1e-12, (pose.name, k)
    assert r.AP == max(p.AP for p in r.poses)
    assert json.loads(r.to_json())["poses"]["P2"]["RP_nm"] == pytest.approx(r.poses[1].RP * 1e9)


def test_iso9283_drift_compares_first_and_last_cycles():
    att = np.array(ATT_9283) * UM
    r = iso9283.evaluate(np.array(CMD_9283) * UM, att, drift_block=3)
    for k, pose in enumerate(r.poses):
        first = hand_9283([CMD_9283[k]], [ATT_9283[k][:3]])[0]
        last = hand_9283([CMD_9283[k]], [ATT_9283[k][3:]])[0]
        assert abs(pose.dAP / UM - abs(first["AP"] - last["AP"])) <= 1e-12
        assert abs(pose.dRP / UM - abs(first["RP"] - last["RP"])) <= 1e-12
    with pytest.raises(ValueError, match="drift block"):
        iso9283.evaluate(np.array(CMD_9283), att, drift_block=4)


def test_iso9283_refuses_a_missing_reading():
    att = np.array(ATT_9283)
    att[1, 4, 2] = np.nan
    with pytest.raises(ValueError, match="pose P2: attained position of cycle 4"):
        iso9283.evaluate(np.array(CMD_9283), att)


def test_rp_gaussian_constant():
    # chi with 3 dof: mean 2 sqrt(2/pi), std sqrt(3 - 8/pi)
    assert rp_gaussian(1.0, 10**6) == pytest.approx(
        2 * math.sqrt(2 / math.pi) + 3 * math.sqrt(3 - 8 / math.pi), rel=1e-5)
    assert rp_gaussian(1.0, 10**6) == pytest.approx(3.616, abs=5e-4)
    assert c4(5) == pytest.approx(0.939986, abs=1e-6)          # the tabulated c4(5)


def test_gaussian_rp_and_r_up_match_their_predictions():
    """Reading noise only: the mean RP over many poses -> rp_gaussian (chi, 3 dof), the mean
    per-target R_i up -> 4 c4(n) sigma (E[s] = c4 sigma)."""
    rng = np.random.default_rng(2024)
    sigma = 5e-9
    att = rng.normal(0.0, sigma, (400, 30, 3))
    r = iso9283.evaluate(np.zeros((400, 3)), att)
    rp = np.mean([p.RP for p in r.poses])
    assert rp == pytest.approx(rp_gaussian(sigma, 30), rel=0.02)
    n = 5
    up = rng.normal(0.0, sigma, (2000, n))
    r2 = iso230_2.evaluate(np.arange(2000), up, up[::-1])
    assert np.mean(r2.R_up_i) == pytest.approx(r_gaussian(sigma, n), rel=0.02)


def test_iso230_3_worked_example_agrees_with_plain_loops():
    t = [0.0, 600.0, 1200.0, 1800.0, 2400.0, 3000.0]
    T = [20.00, 20.10, 20.25, 20.30, 20.20, 20.05]
    d = [0.0, 12.0, 31.0, 38.0, 22.0, 9.0]           # nm
    r = iso230_3.evaluate(t, {"x": np.array(d) * 1e-9}, {"room": T}, "room")
    n = len(t)
    Tm, dm = sum(T) / n, sum(d) / n
    sxy = sum((a - Tm) * (b - dm) for a, b in zip(T, d))
    sxx = sum((a - Tm) ** 2 for a in T)
    b = sxy / sxx
    res = [y - (dm + b * (x - Tm)) for x, y in zip(T, d)]
    se = math.sqrt(sum(e * e for e in res) / (n - 2) / sxx)
    x = r.directions[0]
    assert abs(x.etve * 1e9 - (max(d) - min(d))) <= 1e-12
    assert abs(x.drift * 1e9 - (d[-1] - d[0])) <= 1e-12
    assert abs(x.slope_m_per_K * 1e9 - b) <= 1e-12 * abs(b)
    assert abs(x.slope_std_m_per_K * 1e9 - se) <= 1e-12 * se
    assert abs(r.temperature_range_K["room"] - (max(T) - min(T))) <= 1e-12
    assert json.loads(r.to_json())["directions"]["x"]["ETVE_nm"] == pytest.approx(38.0)
    with pytest.raises(ValueError, match="reference sensor 'air'"):
        iso230_3.evaluate(t, {"x": d}, {"room": T}, "air")
