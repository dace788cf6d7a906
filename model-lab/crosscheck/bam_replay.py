#!/usr/bin/env python3
"""Independent open-loop replay of measured STS3250 pendulum runs (stdlib only).

Written from the servo model's equations alone (firmware ticks every 1 ms holding the duty,
exact integration between them, Coulomb friction with a stick band), without reading the Rust
code, as an independent check of the Rust replay (`model_lab::motion::simulate`);
`model-lab/tests/motion.rs` quotes its figures. Usage: python3 model-lab/crosscheck/bam_replay.py [data_dir]
"""
import glob
import json
import math
import os
import sys

# ---- constants (output-shaft referred) ----
R = 12.0 / 4.2                       # ohm
KT = 50.0 * 0.0980665 / 4.2          # N*m/A
KE = 12.0 / 5.2                      # V*s/rad
JA = 0.040                           # kg*m^2 armature
C_FRIC = 0.08                        # N*m Coulomb
BV = 0.09                            # N*m*s/rad viscous
Q = 2.0 * math.pi / 4096.0           # encoder step (rad)
G = 9.81
OMEGA_EPS = 1e-3                     # rad/s, "at rest" threshold for friction sign

STATS = {"guarded_no_cross": 0, "stops": 0, "sticks": 0}


def sign(x):
    return 1.0 if x > 0 else (-1.0 if x < 0 else 0.0)


def quantize_goal(goal):
    # round half away from zero (only matters at exact .5, which does not occur here)
    x = 2048.0 + goal / Q
    n = math.floor(x + 0.5) if x >= 0 else -math.floor(-x + 0.5)
    n = max(0, min(4095, int(n)))
    return (n - 2048) * Q


def free_motion(omega0, P, D, J, t):
    """Exact solution of J*dw/dt = P - D*w over time t. Returns (omega, distance)."""
    if D * t / J < 1e-9:
        a = (P - D * omega0) / J
        return omega0 + a * t, omega0 * t + 0.5 * a * t * t
    w_inf = P / D
    x = -D * t / J
    e = math.exp(x)
    one_minus_e = -math.expm1(x)
    omega = w_inf + (omega0 - w_inf) * e
    dist = w_inf * t + (omega0 - w_inf) * one_minus_e * J / D
    return omega, dist


def stop_time(omega0, P, D, J, h):
    """Time at which omega(t) = 0 (assumes it happens in (0, h])."""
    if D * h / J < 1e-9:
        a = (P - D * omega0) / J
        return -omega0 / a
    w_inf = P / D
    # w_inf + (omega0 - w_inf) e^{-Dt/J} = 0  ->  e^{-Dt/J} = w_inf / (w_inf - omega0)
    ratio = w_inf / (w_inf - omega0)
    return -(J / D) * math.log(ratio)


def step(theta, omega, h, F, be, J, m, l):
    """Advance (theta, omega) by h with constant drive F and motor damping be."""
    theta_mid = theta + 0.5 * h * omega
    tau_g = m * G * l * math.sin(theta_mid)
    D = be + BV
    Fg = F - tau_g
    if abs(omega) >= OMEGA_EPS:
        s = sign(omega)
    else:
        net = Fg - D * omega
        if abs(net) <= C_FRIC:
            STATS["sticks"] += 1
            return theta, 0.0
        s = sign(net)
    P = Fg - s * C_FRIC
    w_h, d_h = free_motion(omega, P, D, J, h)
    if w_h * s < 0:
        if omega * s > 0:
            STATS["stops"] += 1
            ts = stop_time(omega, P, D, J, h)
            ts = min(max(ts, 0.0), h)
            _, d_s = free_motion(omega, P, D, J, ts)
            theta += d_s
            if abs(Fg) <= C_FRIC:
                return theta, 0.0
            s2 = sign(Fg)
            P2 = Fg - s2 * C_FRIC
            w2, d2 = free_motion(0.0, P2, D, J, h - ts)
            return theta + d2, w2
        # omega started (slightly, |omega|<1e-3) on the opposite side of s and
        # has not reached zero within this step: no zero crossing "against s"
        # occurs, so just integrate the linear law.
        STATS["guarded_no_cross"] += 1
    return theta + d_h, w_h


def simulate(run, tick_dt):
    m = float(run["mass"])
    l = float(run["length"])
    kp = float(run["kp"])
    J = JA + m * l * l
    ent = run["entries"]
    t0 = ent[0]["timestamp"]
    ts = [e["timestamp"] - t0 for e in ent]

    theta = float(ent[0]["position"])
    omega = 0.0
    duty = 0.0
    torque = bool(ent[0]["torque_enable"])
    goal_q = 0.0
    volts = float(ent[0]["input_volts"])
    n_tick = 0

    out = [theta]
    for k in range(len(ent)):
        if k > 0:
            out.append(theta)  # angle reached at t_k, before commands of sample k
        if k == len(ent) - 1:
            break
        # commands of sample k
        e = ent[k]
        goal_q = quantize_goal(float(e["goal_position"]))
        torque = bool(e["torque_enable"])
        volts = float(e["input_volts"])
        t = ts[k]
        t_end = ts[k + 1]
        while t < t_end:
            tick_t = n_tick * tick_dt
            if tick_t <= t:
                # firmware tick
                if torque:
                    duty = kp * 0.166 * (goal_q - theta)
                    duty = max(-0.97, min(0.97, duty))
                else:
                    duty = 0.0
                n_tick += 1
                tick_t = n_tick * tick_dt
            t_next = min(tick_t, t_end)
            h = t_next - t
            if duty != 0.0 or torque:
                F = KT * duty * volts / R
                be = KT * KE / R
            else:
                F = 0.0
                be = 0.0
            theta, omega = step(theta, omega, h, F, be, J, m, l)
            t = t_next
    return out


def errors(run, sim):
    meas = [float(e["position"]) for e in run["entries"]]
    err = [s - p for s, p in zip(sim, meas)]
    n = len(err)
    mae = sum(abs(x) for x in err) / n
    rms = math.sqrt(sum(x * x for x in err) / n)
    return mae, rms, n


def main():
    d = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "..", "..", "data", "bam-sts3250")
    files = sorted(glob.glob(os.path.join(d, "*.json")))
    print("%-26s %5s %6s %4s %5s %11s %11s %15s %15s" % (
        "file", "mass", "length", "kp", "n", "MAE_1ms", "RMS_1ms", "MAE_0.1ms", "RMS_0.1ms"))
    for f in files:
        with open(f) as fh:
            run = json.load(fh)
        mae1, rms1, n = errors(run, simulate(run, 1e-3))
        mae01, rms01, _ = errors(run, simulate(run, 1e-4))
        print("%-26s %5g %6g %4g %5d %11s %11s %15s %15s" % (
            os.path.basename(f), run["mass"], run["length"], run["kp"], n,
            *("%#.4g" % v for v in (mae1, rms1, mae01, rms01))))
    print("diagnostics:", STATS, file=sys.stderr)


if __name__ == "__main__":
    main()
