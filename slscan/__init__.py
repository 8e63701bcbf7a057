"""The slscan application: the command line and the bench station, above every other
package (`scanner`, `calibration`, `inspection`, `sim`)."""
