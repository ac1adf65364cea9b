"""asgp_ros: motion prediction for a smart powered wheelchair (Fan et al., ICRA 2018)."""

__version__ = "0.1.0"
