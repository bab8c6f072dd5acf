"""Studies over captures: the EMVA 1288 datasheet, error-against-time convergence, the paper's SNR formulas."""
