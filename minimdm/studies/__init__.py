"""The study harnesses that produce the book's tables and figures.

They train and compare several methods and format the results; chapters and benchmarks import
them alike. No algorithm lives here, and no algorithm module imports from here.
"""
