"""Numbers and arrays only: the unicycle and its predictors, features and stage cost, the
critics and their TD fit, the actor (its problem, its CasADi NLP, its step), Algorithm 1 over
Protocols, frames, statistics, arrival and parking rules, the TurtleBot3 models, fleet layout.

Imports ``common`` only from math/ and system/; no I/O, no settings, no transport.
"""
