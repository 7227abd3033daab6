"""Kinematics of the body model with Pinocchio, shared by emulators and gateway."""
