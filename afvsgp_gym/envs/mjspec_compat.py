"""MjSpec attribute setters that work on every supported MuJoCo release (3.3 to 4.x).

From MuJoCo 3.7 on, some joint attributes (``damping``, ``stiffness``) are polynomial
coefficient vectors, linear term first (``MjsJoint.damping = [d1, d2, d3]`` compiles to
``dof_damping = d1`` and ``dof_dampingpoly = [d2, d3]``); up to 3.6 they are floats. Assigning
a float to the vector form raises ``TypeError``, so a linear coefficient is written through
:func:`set_linear_coefficient`, which looks at the attribute's current form.
"""

from __future__ import annotations

import numpy as np


def set_linear_coefficient(element: object, attribute: str, value: float) -> None:
    """Set ``element.attribute`` to the linear coefficient ``value`` (higher-order terms 0).

    ``element`` is an MjSpec element (e.g. an ``MjsJoint``); the attribute is a float in
    older MuJoCo releases and a coefficient vector, linear term first, in newer ones.
    """
    value = float(value)
    current = getattr(element, attribute)
    if np.ndim(current) == 0:
        setattr(element, attribute, value)
        return
    coefficients = np.zeros(np.size(current))
    coefficients[0] = value
    setattr(element, attribute, coefficients)
