"""Temporary re-exports for the layout merge."""

from autocal.edges.lab_checks import check_edges2_loads  # noqa: F401
from autocal.edges.noise_waves import expected_auto_model  # noqa: F401
from autocal.edges.simulated_day import simulate_edges_day  # noqa: F401
from autocal.edges.solutions import ReceiverCalError, load_receiver_solution  # noqa: F401
