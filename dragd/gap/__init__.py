"""Model-gap workflow (``dragd gap``, docs/GAP.md): find where the model and the measured current disagree, name the
missing physical effect from a catalogue, add it to the params file, and show the gap shrink.

- ``context``   the measured log at the work rate (reusing dragd/identify/data.py) + rigid-body terms, masks, passes
- ``baseline``  the model as given (a params file) or seed 000's structure fitted on the data
- ``effects``   the catalogue: each effect = regressor columns + signature + params writer
- ``localise``  where the residual lives (joint, phase, velocity, angle spectrum, gravity load, time, even/odd)
- ``select``    forward selection with pass-wise cross-validation and BIC, the stopping rule
- ``report``    PNG residual plots and a markdown report
- ``run``       the whole workflow and its JSON
"""

# the catalogue's effects in selection order, for the command line without importing the workflow (scipy);
# dragd.gap.effects builds CATALOGUE in this order and refuses to import if the two differ
EFFECT_NAMES = ("viscous_friction", "stribeck", "position_periodic", "load_dependent_friction", "inertia",
                "temperature_drift", "backlash", "back_emf", "payload_mass", "current_offset", "coulomb_friction",
                "torque_constant")
