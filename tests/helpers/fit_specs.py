"""The spec the fitting tests share: an Ornstein–Uhlenbeck rate θ read through x with discrete readings."""

OU = '''
name = "ou-fit"
state = ["x"]
drift = ["-theta*x"]
observation = ["x"]
observation_noise = [[0.09]]
parameters = { theta = 0.5 }
[measurement]
kind = "discrete"
[initial]
kind = "gaussian"
mean = [0.0]
cov = [[1.0]]
[domain]
radius = 8.0
[discretization]
dt = 0.01
basis = 32
'''
