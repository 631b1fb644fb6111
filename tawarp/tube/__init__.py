"""The lab's measurement front end: from microphone signals in an impedance tube to the
T-matrix, surface-impedance and core CSVs that ``tawarp fit`` and ``tawarp loop`` read.

:mod:`.spectra` turns time signals into averaged cross-spectra with their random error
(Welch; Bendat & Piersol); the methods (ASTM E2611, ISO 10534-2, the impedance-sensor
multi-termination method) work on those spectra.
"""
