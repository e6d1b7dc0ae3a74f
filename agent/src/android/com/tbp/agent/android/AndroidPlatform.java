package com.tbp.agent.android;

import android.content.Context;
import android.hardware.camera2.CameraManager;
import android.os.Build;
import com.tbp.agent.Agent;
import com.tbp.agent.CameraBackend;
import com.tbp.agent.ImageStore;
import com.tbp.agent.Log;
import com.tbp.agent.Platform;
import java.io.Closeable;
import java.io.File;
import java.io.IOException;
import java.lang.reflect.Constructor;

/**
 * The agent on a phone: Camera2 through a CameraManager made for the shell's package, the image
 * folder {@value ImageStore#PHONE_FOLDER}, an abstract socket, logcat. Android 12 (API 31) or newer:
 * before it the camera service refuses a camera to a process such as app_process's that has no
 * app in the foreground (scrcpy refuses camera mirroring there for this reason).
 */
public final class AndroidPlatform implements Platform {

    public static final int MIN_SDK = 31;

    private final Log log = new LogcatLog();

    @Override
    public Log log() {
        return log;
    }

    @Override
    public CameraBackend openCamera(double exposureS, long iso) throws Exception {
        if (Build.VERSION.SDK_INT < MIN_SDK) {
            throw new Exception("the camera needs Android 12 (API " + MIN_SDK + ") or newer from app_process; this"
                    + " phone runs API " + Build.VERSION.SDK_INT);
        }
        CameraManager manager = cameraManager();
        Camera2Config config = Camera2Config.choose(manager, exposureS, iso, Build.MODEL, serial());
        return Camera2Backend.open(manager, config, log);
    }

    /** CameraManager's constructor taking a Context is the framework's own (hidden); reached by reflection. */
    private static CameraManager cameraManager() throws ReflectiveOperationException {
        Constructor<CameraManager> constructor = CameraManager.class.getDeclaredConstructor(Context.class);
        constructor.setAccessible(true);
        return constructor.newInstance(FakeContext.get());
    }

    /** ro.serialno, the serial adb reports and the controller checks (SystemProperties is hidden API). */
    private String serial() {
        try {
            Class<?> properties = Class.forName("android.os.SystemProperties");
            return (String) properties.getMethod("get", String.class).invoke(null, "ro.serialno");
        } catch (ReflectiveOperationException e) {
            log.error("ro.serialno", e);
            return "unknown";
        }
    }

    @Override
    public ImageStore imageStore() {
        return new ImageStore(new File(ImageStore.PHONE_FOLDER), ImageStore.DISK);
    }

    @Override
    public Closeable listen(String name, Agent agent) throws IOException {
        return LocalSocketListener.start(name, agent, log);
    }
}
