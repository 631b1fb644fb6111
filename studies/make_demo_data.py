"""Make the bundled demo measurement: ceramic core T-matrices with an effect the paper's
model lacks, for ``tawarp demo`` and ``tawarp loop`` to find.

The hidden effect is natural convection in the thermal buffer tube, an exchange
coefficient that grows with the local temperature excess,
``h_a + h_conv theta^(1/4)`` (``tbt.h_convection = 3``): the paper notes that its fitted
h_a depends on the stack material and the heating when it should not. (A temperature-
dependent stack conductivity is nearly indistinguishable from radiative conductivity on
these data, so it makes a poor single demo.) 0.2 % complex noise,
frequencies 50-500 Hz, Q = 0, 40, 80 W, sigma columns give the noise.

    python studies/make_demo_data.py   # writes tawarp/data/measured/ceramic_hidden_effect.csv
"""

import argparse
from pathlib import Path

import numpy as np

from tawarp.model.core import load_core
from tawarp.model.forward import ForwardSettings
from tawarp.measure.synthetic import synthetic_tmatrix
from tawarp.measure.files import write_tmatrix_csv

TRUTH = {"tbt.h_convection": 3.0}
BUNDLED = Path(__file__).resolve().parents[1] / "tawarp" / "data" / "measured" / "ceramic_hidden_effect.csv"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(BUNDLED), help="CSV output (default: the bundled file)")
    args = ap.parse_args(argv)
    data = synthetic_tmatrix(
        load_core("ceramic"),
        TRUTH,
        freqs=np.linspace(50.0, 500.0, 16),
        heat_inputs=(0.0, 40.0, 80.0),
        noise=0.002,
        seed=7,
        settings=ForwardSettings(device="cpu", cells=24),
    )
    write_tmatrix_csv(
        args.out, data, metadata={"core": "ceramic", "hidden_effect": "none declared (see studies/make_demo_data.py)"}
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
