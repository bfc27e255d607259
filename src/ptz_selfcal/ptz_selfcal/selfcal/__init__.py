"""Self-calibration from homographies: linear IAC (section 3.3.2), LM on eq. 22 (3.3.1), DIAC transfer
(eq. 20), degeneracy (6), and the result every method returns."""
