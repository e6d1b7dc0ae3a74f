package com.tbp.agent.android;

import android.graphics.ImageFormat;
import android.hardware.camera2.CameraAccessException;
import android.hardware.camera2.CameraCharacteristics;
import android.hardware.camera2.CameraManager;
import android.hardware.camera2.params.StreamConfigurationMap;
import android.util.Range;
import android.util.Size;
import com.tbp.agent.CameraBackend;

/**
 * The back main camera and how the agent drives it, from its characteristics: the first
 * back-facing camera in CameraManager's list (camera "0" on most phones; a logical multi-camera
 * is used as the list names it), which must have MANUAL_SENSOR (manual exposure and lens). The
 * still is the largest JPEG size of its stream configuration (the sensor's full or default binned
 * resolution; high-resolution-only sizes are not used); the repeating request feeds a small YUV
 * stream that is read and dropped.
 */
final class Camera2Config {

    /** The rig's manual exposure (calibration_data/rig.yaml optics), unless the start command sets one. */
    static final double DEFAULT_EXPOSURE_S = 0.002;
    static final long DEFAULT_ISO = 50;
    /** The repeating stream's smallest acceptable size (it carries only lens state and timestamps). */
    static final int PREVIEW_MIN_PIXELS = 320 * 240;

    final String cameraId;
    final CameraBackend.Info info;
    final Size jpegSize;
    final Size previewSize;
    /** SENSOR_INFO_TIMESTAMP_SOURCE REALTIME: sensor timestamps are CLOCK_BOOTTIME. */
    final boolean realtimeClock;

    private Camera2Config(String cameraId, CameraBackend.Info info, Size jpegSize, Size previewSize,
                          boolean realtimeClock) {
        this.cameraId = cameraId;
        this.info = info;
        this.jpegSize = jpegSize;
        this.previewSize = previewSize;
        this.realtimeClock = realtimeClock;
    }

    /**
     * @param exposureS the start command's exposure (s), 0 for {@link #DEFAULT_EXPOSURE_S} (clamped to the sensor)
     * @param iso       the start command's ISO, 0 for {@link #DEFAULT_ISO} (clamped to the sensor)
     */
    static Camera2Config choose(CameraManager manager, double exposureS, long iso, String model, String serial)
            throws CameraAccessException, CameraUnsuitable {
        String chosen = null;
        CameraCharacteristics camera = null;
        for (String id : manager.getCameraIdList()) {
            CameraCharacteristics characteristics = manager.getCameraCharacteristics(id);
            Integer facing = characteristics.get(CameraCharacteristics.LENS_FACING);
            if (facing != null && facing == CameraCharacteristics.LENS_FACING_BACK) {
                chosen = id;
                camera = characteristics;
                break;
            }
        }
        if (chosen == null) {
            throw new CameraUnsuitable("no back-facing camera");
        }
        if (!has(camera.get(CameraCharacteristics.REQUEST_AVAILABLE_CAPABILITIES),
                CameraCharacteristics.REQUEST_AVAILABLE_CAPABILITIES_MANUAL_SENSOR)) {
            throw new CameraUnsuitable("camera " + chosen + " lacks MANUAL_SENSOR (manual exposure and focus)");
        }
        StreamConfigurationMap streams = camera.get(CameraCharacteristics.SCALER_STREAM_CONFIGURATION_MAP);
        Size jpeg = largest(streams.getOutputSizes(ImageFormat.JPEG));
        Size preview = smallestAtLeast(streams.getOutputSizes(ImageFormat.YUV_420_888), PREVIEW_MIN_PIXELS);
        if (jpeg == null || preview == null) {
            throw new CameraUnsuitable("camera " + chosen + " lists no JPEG or no YUV_420_888 output size");
        }
        Float minFocus = camera.get(CameraCharacteristics.LENS_INFO_MINIMUM_FOCUS_DISTANCE);
        Integer calibration = camera.get(CameraCharacteristics.LENS_INFO_FOCUS_DISTANCE_CALIBRATION);
        Integer source = camera.get(CameraCharacteristics.SENSOR_INFO_TIMESTAMP_SOURCE);
        boolean realtime = source != null && source == CameraCharacteristics.SENSOR_INFO_TIMESTAMP_SOURCE_REALTIME;
        Range<Long> exposureNs = camera.get(CameraCharacteristics.SENSOR_INFO_EXPOSURE_TIME_RANGE);
        Range<Integer> sensitivity = camera.get(CameraCharacteristics.SENSOR_INFO_SENSITIVITY_RANGE);
        double minExposure = exposureNs.getLower() / 1e9;
        double maxExposure = exposureNs.getUpper() / 1e9;
        long minIso = sensitivity.getLower();
        long maxIso = sensitivity.getUpper();
        double exposure = chosenValue(exposureS, DEFAULT_EXPOSURE_S, minExposure, maxExposure, "exposure_s");
        long chosenIso = Math.round(chosenValue(iso, DEFAULT_ISO, minIso, maxIso, "iso"));
        CameraBackend.Info info = new CameraBackend.Info(model, serial, minFocus == null ? 0.0 : minFocus,
                calibration == null ? 0 : calibration, realtime ? "realtime" : "unknown", exposure, chosenIso,
                jpeg.getWidth(), jpeg.getHeight(), minExposure, maxExposure, minIso, maxIso);
        return new Camera2Config(chosen, info, jpeg, preview, realtime);
    }

    /** The start command's value, which must lie in the sensor's range, or the default, clamped to it. */
    private static double chosenValue(double given, double fallback, double low, double high, String name)
            throws CameraUnsuitable {
        if (given > 0 && (given < low || given > high)) {
            throw new CameraUnsuitable(name + "=" + given + " outside the sensor's [" + low + ", " + high + "]");
        }
        double value = given > 0 ? given : fallback;
        return Math.min(Math.max(value, low), high);
    }

    private static boolean has(int[] values, int wanted) {
        if (values != null) {
            for (int value : values) {
                if (value == wanted) {
                    return true;
                }
            }
        }
        return false;
    }

    private static Size largest(Size[] sizes) {
        Size best = null;
        for (Size size : sizes == null ? new Size[0] : sizes) {
            if (best == null || pixels(size) > pixels(best)) {
                best = size;
            }
        }
        return best;
    }

    private static Size smallestAtLeast(Size[] sizes, long minPixels) {
        Size best = null;
        for (Size size : sizes == null ? new Size[0] : sizes) {
            boolean enough = pixels(size) >= minPixels;
            if (best == null || (enough && (pixels(best) < minPixels || pixels(size) < pixels(best)))
                    || (!enough && pixels(best) < minPixels && pixels(size) > pixels(best))) {
                best = size;
            }
        }
        return best;
    }

    private static long pixels(Size size) {
        return (long) size.getWidth() * size.getHeight();
    }

    /** The phone's camera cannot do what the agent needs; the message says what is missing. */
    static final class CameraUnsuitable extends Exception {

        private static final long serialVersionUID = 1L;

        CameraUnsuitable(String message) {
            super(message);
        }
    }
}
