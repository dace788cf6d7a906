#!/usr/bin/env python3
"""Telemetry sessions of servo chains written from the physics, sharing no code with the model
lab (Python's standard library only), for judging the lab on effects outside its catalog.

Each session: 4-8 servos on one chain, 2 h at 1 Hz, in the telemetry CSV format of
data/README.md (t_s, motor, voltage_v, temperature_c, current_a). Each servo's winding is one
thermal mass C heated by its copper loss I^2 R and its electronics' P0, and loses heat to the air:

  none          Newton's cooling, (T - T_air) / R_th: the lab's nominal model, nothing hidden.
  convection    natural convection, h (T - T_air)^1.25 (laminar free convection: the loss grows
                faster than the rise), h set so the loss matches R_th at a 15 K rise.
  cooling_step  Newton's cooling until a random time in the second hour, then R_th 40-80 %
                higher for every servo at once (a fan stops).

The servos work in stretches of 2-12 min and hold still between them (a few tens of mA), so
the sessions have regimes a named effect must hold in. Registers: temperature in whole degrees,
current in 6.5 mA steps with 10 mA of noise, supply 12 V +- noise in 0.1 V steps.

Usage: independent_sessions.py OUT.csv --effect EFFECT --seed N
Prints the truth (the effect and its drawn sizes) as one JSON line.
"""

import argparse
import json
import math
import random

AIR_C = (20.0, 28.0)
PERIOD_S = 1.0
DURATION_S = 7200.0
SUBSTEPS = 4


def draw_servos(rng, n):
    servos = []
    for _ in range(n):
        servos.append(
            {
                "heat_capacity": rng.uniform(150.0, 350.0),  # J/K
                "resistance": rng.uniform(3.0, 5.0),  # ohm, winding + driver
                "r_th": rng.uniform(2.0, 4.0),  # K/W to the air
                "p0": rng.uniform(0.2, 0.5),  # W, electronics
                "warm": rng.uniform(0.0, 3.0),  # K above equilibrium at the start
            }
        )
    return servos


def draw_currents(rng, steps):
    """Signed motor current per sample: work stretches and holds between them."""
    out = []
    while len(out) < steps:
        length = int(rng.uniform(120.0, 720.0) / PERIOD_S)
        if rng.random() < 0.4:
            hold = rng.uniform(0.02, 0.08)
            out.extend(hold for _ in range(length))
        else:
            amp = rng.uniform(0.5, 1.8)
            sign = 1.0 if rng.random() < 0.5 else -1.0
            flip_in = rng.uniform(2.0, 10.0)
            for _ in range(length):
                flip_in -= PERIOD_S
                if flip_in <= 0.0:
                    sign = -sign
                    flip_in = rng.uniform(2.0, 10.0)
                out.append(sign * amp * (1.0 + 0.08 * rng.gauss(0.0, 1.0)))
    return out[:steps]


def loss_w(effect, servo, rise, t, step_at, step_factor):
    """Heat lost to the air, W, at a winding `rise` K above it."""
    if effect == "convection":
        # h chosen so that h * 15^1.25 = 15 / R_th.
        h = (15.0 / servo["r_th"]) / 15.0**1.25
        return h * math.copysign(abs(rise) ** 1.25, rise)
    r_th = servo["r_th"]
    if effect == "cooling_step" and t >= step_at:
        r_th *= step_factor
    return rise / r_th


def session(effect, seed):
    rng = random.Random(seed * 7919 + 17)
    n = rng.randint(4, 8)
    air = rng.uniform(*AIR_C)
    servos = draw_servos(rng, n)
    steps = int(DURATION_S / PERIOD_S)
    currents = [draw_currents(rng, steps) for _ in range(n)]
    step_at = rng.uniform(3600.0, 6600.0)
    step_factor = rng.uniform(1.4, 1.8)
    rows = []
    temps = [air + s["p0"] * s["r_th"] + s["warm"] for s in servos]
    h = PERIOD_S / SUBSTEPS
    for k in range(steps):
        t = k * PERIOD_S
        volts = round((12.0 + rng.gauss(0.0, 0.03)) * 10.0) / 10.0
        for m, s in enumerate(servos):
            i = currents[m][k]
            measured_i = round((i + rng.gauss(0.0, 0.01)) / 0.0065) * 0.0065
            rows.append((t, m + 1, volts, round(temps[m]), measured_i))
            heat = i * i * s["resistance"] + s["p0"]
            # Classic Runge-Kutta over the sample period (the loss is nonlinear).
            T = temps[m]
            for j in range(SUBSTEPS):
                tj = t + j * h

                def dT(T, tt):
                    return (heat - loss_w(effect, s, T - air, tt, step_at, step_factor)) / s[
                        "heat_capacity"
                    ]

                k1 = dT(T, tj)
                k2 = dT(T + 0.5 * h * k1, tj + 0.5 * h)
                k3 = dT(T + 0.5 * h * k2, tj + 0.5 * h)
                k4 = dT(T + h * k3, tj + h)
                T += h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            temps[m] = T
    truth = {"effect": effect, "seed": seed, "motors": n, "air_c": air}
    if effect == "cooling_step":
        truth.update({"step_at_s": step_at, "r_th_factor": step_factor})
    return rows, truth


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out")
    p.add_argument("--effect", choices=["none", "convection", "cooling_step"], required=True)
    p.add_argument("--seed", type=int, required=True)
    a = p.parse_args()
    rows, truth = session(a.effect, a.seed)
    with open(a.out, "w") as f:
        f.write("t_s,motor,voltage_v,temperature_c,current_a\n")
        for t, m, v, temp, i in rows:
            f.write(f"{t:.1f},{m},{v:.1f},{temp},{i:.4f}\n")
    print(json.dumps(truth))


if __name__ == "__main__":
    main()
