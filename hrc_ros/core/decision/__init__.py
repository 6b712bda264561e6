"""What the decision layer does each epoch, outside the solvers: human motion into the velocity
level O and the distance level d (`observation`), and an action from the belief and the
observable state (`selection`: paper, qmdp, mls, mdp, pomdp, fib)."""
