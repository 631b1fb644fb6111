"""tawarp: thermoacoustic core T-matrices, batched parameter estimation and design on NVIDIA Warp."""

from .model.core import Core, CoreError, Gas, Segment, bundled_cores, load_core, paper_cores
from .model.forward import Engine, ForwardResult, ForwardSettings, steady_temperature, transfer_matrices

__all__ = [
    "Core",
    "CoreError",
    "Gas",
    "Segment",
    "bundled_cores",
    "load_core",
    "paper_cores",
    "Engine",
    "ForwardResult",
    "ForwardSettings",
    "steady_temperature",
    "transfer_matrices",
]
__version__ = "0.1.0"
