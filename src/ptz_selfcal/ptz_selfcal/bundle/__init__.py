"""Bundle adjustment over keyframes (section 5): observations, residuals, Schur solve, covariance."""
