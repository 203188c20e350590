"""Angle of arrival: the operator, joint angle-delay MUSIC and the array model."""
