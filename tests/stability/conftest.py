"""The numerical-stability suite: hard cases that must stay finite (see docs/performance.md).

The fast cases run in every ``make test``; the long ones (1000-step rollouts of every pybullet
scene, trained-checkpoint rollouts, 10x impacts on real scenes) run only with ``HRN_SLOW=1``
(``make test-slow``).
"""

