"""Reports and plots."""

from jaxcal.report.plots import plot_convergence, plot_errors_before_after, save_atomic, write_text_atomic

__all__ = ["plot_convergence", "plot_errors_before_after", "save_atomic", "write_text_atomic"]
