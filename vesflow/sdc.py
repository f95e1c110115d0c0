"""The SDC steps (vesflow.stepping.sdc), under their former name."""
from .stepping.sdc import (QUADRATURES, RHO_MAX, SDC, collocation_order, error_estimate,  # noqa: F401
                           integration_matrix, lobatto_nodes, radau_nodes)
